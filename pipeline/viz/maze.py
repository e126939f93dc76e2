"""The maze as Rerun 2D entities, in world coordinates (environment units, x right, y up)."""

from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

WALL_COLOR = (90, 90, 100)


def wall_boxes(layout: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Centres `[W, 2]` and half sizes `[W, 2]` (world units) of the wall cells of a maze layout."""
    scale = float(layout["maze_size_scaling"])
    rows, cols = np.asarray(layout["wall_cells"], dtype=float).reshape(-1, 2).T
    centers = np.stack(
        [
            cols * scale - layout["x_map_center"] + scale / 2,
            layout["y_map_center"] - rows * scale - scale / 2,
        ],
        axis=1,
    )
    return centers, np.full_like(centers, scale / 2)


def log_maze(rec: rr.RecordingStream, layout: dict[str, Any], entity: str = "maze") -> None:
    """Log the walls (static: valid on every timeline) under `entity/walls`."""
    centers, half = wall_boxes(layout)
    rec.log(
        f"{entity}/walls",
        rr.Boxes2D(centers=centers, half_sizes=half, colors=WALL_COLOR, draw_order=0.0),
        static=True,
    )


def maze_view(origin: str = "/", name: str = "maze") -> rrb.Spatial2DView:
    """A 2D view of the maze and everything logged beside it."""
    return rrb.Spatial2DView(origin=origin, name=name)
