"""OGBench's dataset recipes (`data_gen_scripts/generate_locomaze.py`, `commands.sh`): dataset
types, action noise, and the start and goal cell pools."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.envs.ogbench import check_ogbench_id
from pipeline.errors import UserError

DATASET_TYPES = ("navigate", "stitch", "explore")
# OGBench's action noise std per locomotor and dataset type (`commands.sh`: the point's
# navigate / stitch use --noise=0.5, the ant's keep the script's default 0.2; explore: 1.0).
NOISE = {
    "point": {"navigate": 0.5, "stitch": 0.5, "explore": 1.0},
    "ant": {"navigate": 0.2, "stitch": 0.2, "explore": 1.0},
}
POINT_NOISE = NOISE["point"]
# `stitch` goals lie this many BFS steps from the start cell.
STITCH_CELLS = 4
# `explore` redraws its direction every this many steps.
EXPLORE_EVERY = 10


@dataclass(frozen=True)
class Recipe:
    """One OGBench dataset recipe: maze, type, sizes, noise, seed and (ant) expert file."""

    env_id: str
    dataset_type: str
    episodes: int
    episode_steps: int
    noise: float
    seed: int
    expert: str | None = None
    """The ant expert's actor (`.safetensors`, its `.json` beside it); None for the point."""

    @property
    def loco(self) -> str:
        """The locomotor: "point" or "ant"."""
        return check_ogbench_id(self.env_id)[0]

    def to_dict(self) -> dict[str, Any]:
        return {
            "recipe": "OGBench data_gen_scripts/generate_locomaze.py",
            "dataset_type": self.dataset_type,
            "n_episodes": self.episodes,
            "episode_steps": self.episode_steps,
            "noise": self.noise,
            "continuous": False,
        }


def make_recipe(
    env_id: str,
    dataset_type: str,
    episodes: int,
    episode_steps: int,
    seed: int,
    noise: float | None = None,
    expert: str | None = None,
) -> Recipe:
    """Checked recipe; `noise` None: OGBench's for the locomotor and dataset type.

    Raises:
        UserError: an unsupported maze or dataset type, sizes below 1 episode of 2 steps, an ant
            maze without `expert`, or a point maze with one (the point's oracle acts itself).
    """
    loco, _ = check_ogbench_id(env_id)
    if dataset_type not in DATASET_TYPES:
        raise UserError(
            f"unknown OGBench dataset type {dataset_type!r}; use one of: {', '.join(DATASET_TYPES)}"
        )
    if episodes < 1 or episode_steps < 2:
        raise UserError(
            f"need episodes >= 1 and episode_steps >= 2, got {episodes}, {episode_steps}"
        )
    if loco == "ant" and not expert:
        raise UserError(
            f"generating {env_id} data needs the ant expert: set ingest.ogbench.expert to its "
            "actor (experts/ant/actor.safetensors; `oposm expert train ant` makes one)"
        )
    if loco == "point" and expert:
        raise UserError(
            f"ingest.ogbench.expert is for ant mazes; {env_id}'s oracle moves the point itself: "
            "set ingest.ogbench.expert to null"
        )
    noise = NOISE[loco][dataset_type] if noise is None else float(noise)
    return Recipe(
        env_id, dataset_type, int(episodes), int(episode_steps), noise, int(seed), expert or None
    )


def maze_cells(maze_map: np.ndarray) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """OGBench's start and goal cell pools: all free cells, and the "vertex" cells, the free
    cells that are not a straight hallway (free above and below with walls left and right, or
    free left and right with walls above and below)."""
    free, vertex = [], []
    m = maze_map
    for (i, j), value in np.ndenumerate(m):
        if value != 0:
            continue
        free.append((i, j))
        vertical = m[i - 1, j] == 0 and m[i + 1, j] == 0 and m[i, j - 1] == 1 and m[i, j + 1] == 1
        across = m[i, j - 1] == 0 and m[i, j + 1] == 0 and m[i - 1, j] == 1 and m[i + 1, j] == 1
        if not (vertical or across):
            vertex.append((i, j))
    return free, vertex


def cells_at_distance(maze_map: np.ndarray, start: tuple[int, int], steps: int) -> list:
    """Free cells exactly `steps` BFS moves (4-neighbour) from `start`, in BFS order."""
    distance = {start: 0}
    queue, found = [start], []
    while queue:
        i, j = queue.pop(0)
        for di, dj in ((-1, 0), (0, -1), (1, 0), (0, 1)):
            cell = (i + di, j + dj)
            inside = 0 <= cell[0] < maze_map.shape[0] and 0 <= cell[1] < maze_map.shape[1]
            if inside and maze_map[cell] == 0 and cell not in distance:
                distance[cell] = distance[(i, j)] + 1
                queue.append(cell)
                if distance[cell] == steps:
                    found.append(cell)
    return found
