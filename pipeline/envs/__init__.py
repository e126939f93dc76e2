"""Environments behind one spec (`spec`), the batched simulator (`batch`), PointMaze helpers
(`maze`), the scripted D4RL-style expert (`expert`), data generation (`generate`), dataset checks
(`checks`), the ant (`ant`, `ant_expert`), OGBench's mazes (`ogbench`) and manipulation envs
(`manipspace`, its data: `manipspace_data`). Import from the modules: a stage then runs (and
lists in dvc.yaml) only the ones it uses."""
