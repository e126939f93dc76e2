"""The ant's direction expert, in one place: the SAC-trained policy that drives OGBench's ant in
a commanded direction, which OGBench's ant data recipe and the `expert` agent steer through a
maze (docs/ant-expert.md). `actor`: the policy's network and its safetensors file (plain torch,
no pickle); `config`: its params (`experts/ant/params.yaml`); `training`: SAC; `check`: its
speed and maze success. `oposm expert train ant` and `oposm expert check ant` run the last two
(`stages/expert.py`)."""
