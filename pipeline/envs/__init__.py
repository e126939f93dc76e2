"""PointMaze environments, the scripted D4RL-style expert, data generation and dataset checks."""

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

__all__ = [
    "SUPPORTED_ENVS",
    "DatasetReport",
    "ExpertConfig",
    "WaypointExpert",
    "cell_to_xy",
    "check_maze_dataset",
    "dataset_info",
    "free_cells",
    "generate_episodes",
    "get_physics_state",
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
