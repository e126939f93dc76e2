"""Rerun logging of mazes, episodes, plans and model predictions (imported lazily: rerun is big);
OGBench's manipulation envs in 3-D (`manip`, `manip_validate`)."""
