"""Environments behind one spec, the batched simulator, the scripted D4RL-style expert, data
generation and dataset checks."""

from pipeline.envs.batch import BatchSim
from pipeline.envs.checks import DatasetReport, check_maze_dataset, raise_for_problems
from pipeline.envs.expert import ExpertConfig, WaypointExpert
from pipeline.envs.generate import dataset_info, generate_episodes
from pipeline.envs.maze import (
    SUPPORTED_ENVS,
    cell_to_xy,
    free_cells,
    get_physics_state,
    make_maze_env,
    max_episode_steps,
    maze_layout,
    maze_of,
    point_env,
    set_physics_state,
    step_point_mass,
    xy_to_cell,
)
from pipeline.envs.spec import EnvSpec, PointMazeSpec, make_env_spec

__all__ = [
    "SUPPORTED_ENVS",
    "BatchSim",
    "DatasetReport",
    "EnvSpec",
    "ExpertConfig",
    "PointMazeSpec",
    "WaypointExpert",
    "cell_to_xy",
    "check_maze_dataset",
    "dataset_info",
    "free_cells",
    "generate_episodes",
    "get_physics_state",
    "make_env_spec",
    "make_maze_env",
    "max_episode_steps",
    "maze_layout",
    "maze_of",
    "point_env",
    "raise_for_problems",
    "set_physics_state",
    "step_point_mass",
    "xy_to_cell",
]
