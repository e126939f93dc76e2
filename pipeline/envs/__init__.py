"""Environments behind one spec (`spec`), the batched simulator (`batch`), PointMaze helpers
(`maze`), the scripted D4RL-style expert (`expert`), data generation (`generate`), dataset checks
(`checks`) and the ant (`ant`, `ant_expert`). Import from the modules: a stage then runs (and
lists in dvc.yaml) only the ones it uses."""
