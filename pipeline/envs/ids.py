"""The environments' names and plain constants, in a module that loads no simulator.

The params models (`pipeline.config`) validate env ids and the evaluation code names its tasks
with these; importing them must not start gymnasium, MuJoCo or torch, so that loading
`params.yaml` (`oposm params`, every stage's first step) stays light. The simulator modules
(`maze`, `ogbench`, `manipspace`) import their ids from here and keep them under their own names,
so `pipeline.envs.maze.env.SUPPORTED_ENVS` and the like still work.
"""

from __future__ import annotations

import math
from typing import Any

# PointMaze ids (gymnasium-robotics v3) and their D4RL maze2d step limits (also
# gymnasium-robotics' `max_episode_steps`).
SUPPORTED_ENVS: dict[str, int] = {
    "PointMaze_UMaze-v3": 300,
    "PointMaze_Medium-v3": 600,
    "PointMaze_Large-v3": 800,
}

# OGBench's locomotion maze ids -> (locomotion type, maze type).
OGBENCH_MAZES: dict[str, tuple[str, str]] = {
    f"{loco}maze-{size}-v0": (loco, size)
    for loco in ("point", "ant")
    for size in ("medium", "large", "giant", "teleport")
}

# OGBench's manipulation ids: the cubes, the scene, and the "Lights Out" puzzles (rows x cols).
PUZZLE_ENVS: tuple[str, ...] = tuple(f"puzzle-{g}-v0" for g in ("3x3", "4x4", "4x5", "4x6"))
MANIPSPACE_ENVS: tuple[str, ...] = ("cube-single-v0", "cube-double-v0", "scene-v0", *PUZZLE_ENVS)

# Evaluation task names (`pipeline.evaluation.tasks`). The position of a name is part of every
# episode's seed, so the order is fixed (new names go last); OGBench's task K is reported as
# `ogbench-taskK`, the kitchen's task as its D4RL task set (`kitchen-mixed`, ...).
TASKS = ("corners", "random_goal", "goal", "ogbench", "kitchen")
OGBENCH_PREFIX = "ogbench-"

# A maze grid cell, (row, col).
Cell = tuple[int, int]


def layout_cell(layout: dict[str, Any], x: float, y: float) -> Cell:
    """`(row, col)` of point `(x, y)` from a `maze_layout` dict (same formula as the maze's)."""
    scale = layout["maze_size_scaling"]
    row = math.floor((layout["y_map_center"] - y) / scale)
    col = math.floor((x + layout["x_map_center"]) / scale)
    return row, col
