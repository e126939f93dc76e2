"""Environments behind one spec (`spec`) and the batched simulator (`batch`), one folder or module
per domain: gymnasium-robotics' PointMazes with their expert, data and checks (`maze/`), OGBench's
point and ant mazes (`ogbench`, `ant`, its data controller `ogbench_oracle`), its manipulation
tasks with their data and oracle (`manipspace/`), the Franka kitchen (`kitchen`); the MuJoCo state
they share (`physics`), random pushes (`disturbance`), mass changes (`perturb`) and the env ids
(`ids`, no simulator). The ant's expert is `pipeline.ant_expert`. Import from the modules: a stage
then runs (and lists in dvc.yaml) only the ones it uses."""
