"""D4RL maze2d coordinates to gymnasium-robotics PointMaze coordinates.

D4RL's point maze (`d4rl/pointmaze/maze_model.py`) and gymnasium-robotics' PointMaze v3 are the
same MuJoCo model (point.xml: same mass, damping, gear, timestep, velocity clip) on the same maps,
but placed differently in the world:

- D4RL puts the wall of grid cell (i, j) (row i of the map string, column j) as a unit box at world
  `(i + 1, j + 1)` and the ball's body at `(1.2, 1.2)`, with slide joints along world x and y. So
  the ball is at world `qpos + 1.2`, and cell (i, j)'s centre is at `qpos = (i - 0.2, j - 0.2)`.
  The first coordinate follows the map's rows, the second its columns.
- gymnasium-robotics puts the body at the origin, so `qpos` is the world position, and cell
  (row, col)'s centre at `x = (col + 0.5) * s - x_map_center`, `y = y_map_center - (row + 0.5) * s`
  (`s` = maze_size_scaling = 1 for PointMaze): x follows the columns, y runs against the rows.

Hence, with `c = 0.2 + 0.5`: `x = q1 + c - x_map_center`, `y = y_map_center - c - q0` for
positions (qpos, goals), and `(v1, -v0)` for velocities and forces (actions). It is a rotation by
-90 degrees plus a translation, so the dynamics are unchanged. Published D4RL maze2d-large-v1
observations span `[0.396, 7.216] x [0.442, 10.219]`, which this maps to within 0.02 m of the
free cells' reachable area (tests/test_sources.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.errors import UserError

# The ball's body offset in D4RL's MJCF (1.2) minus the walls' offset (1.0), in cells.
D4RL_BODY_OFFSET = 0.2


@dataclass(frozen=True)
class Maze2dMap:
    """The affine map from D4RL maze2d coordinates to those of a gymnasium-robotics PointMaze.

    Attributes:
        x_offset: `x = q1 + x_offset`.
        y_offset: `y = y_offset - q0`.
    """

    x_offset: float
    y_offset: float

    @classmethod
    def for_layout(cls, layout: dict[str, Any]) -> Maze2dMap:
        """The map for a `maze_layout` (gymnasium-robotics' map centre and cell size)."""
        if float(layout["maze_size_scaling"]) != 1.0:
            raise UserError(
                "D4RL maze2d cells are 1 m wide but this maze has maze_size_scaling "
                f"{layout['maze_size_scaling']}; cannot convert coordinates"
            )
        centre = D4RL_BODY_OFFSET + 0.5
        return cls(
            x_offset=centre - float(layout["x_map_center"]),
            y_offset=float(layout["y_map_center"]) - centre,
        )

    def positions(self, q: np.ndarray) -> np.ndarray:
        """D4RL positions `[N, 2]` (qpos, goals) -> gymnasium-robotics `[N, 2]`."""
        return np.column_stack([q[:, 1] + self.x_offset, self.y_offset - q[:, 0]])

    @staticmethod
    def vectors(v: np.ndarray) -> np.ndarray:
        """D4RL velocities or actions `[N, 2]` -> gymnasium-robotics `[N, 2]` (rotation only)."""
        return np.column_stack([v[:, 1], -v[:, 0]])

    def states(self, s: np.ndarray) -> np.ndarray:
        """D4RL observations `[N, 4]` = (qpos, qvel) -> gymnasium-robotics `[x, y, vx, vy]`."""
        return np.column_stack([self.positions(s[:, :2]), self.vectors(s[:, 2:4])])

    def inverse_positions(self, p: np.ndarray) -> np.ndarray:
        """gymnasium-robotics positions `[N, 2]` -> D4RL (to write D4RL-layout files)."""
        return np.column_stack([self.y_offset - p[:, 1], p[:, 0] - self.x_offset])

    @staticmethod
    def inverse_vectors(v: np.ndarray) -> np.ndarray:
        """gymnasium-robotics velocities or actions `[N, 2]` -> D4RL."""
        return np.column_stack([-v[:, 1], v[:, 0]])

    def inverse_states(self, s: np.ndarray) -> np.ndarray:
        """gymnasium-robotics `[N, 4]` states -> D4RL observations."""
        return np.column_stack([self.inverse_positions(s[:, :2]), self.inverse_vectors(s[:, 2:4])])

    def to_dict(self) -> dict[str, Any]:
        """The mapping as metadata (`DatasetInfo.generator["coordinate_map"]`)."""
        return {
            "from": "d4rl maze2d (qpos of d4rl/pointmaze/maze_model.py)",
            "to": "gymnasium-robotics PointMaze v3",
            "position": f"x = q[1] {self.x_offset:+g}, y = {self.y_offset:g} - q[0]",
            "velocity_and_action": "(v[1], -v[0])",
            "position_matrix": [[0.0, 1.0], [-1.0, 0.0]],
            "position_offset": [self.x_offset, self.y_offset],
            "vector_matrix": [[0.0, 1.0], [-1.0, 0.0]],
        }
