"""The maze in Rerun 2D views, the right way up, and what every map view shares.

Rerun's 2D views draw y downward and ignore view coordinates, while the environment's y points up.
So every 2D position is flipped at logging time (`to_view`: (x, y) -> (x, -y)): the views show x
right, y up, and cell (1, 1) of Medium, world (-2.5, 2.5), lands top-left as in MuJoCo's render and
the paper's figures. (A flipping transform on a parent entity would keep world coordinates in the
data, but Rerun 0.41 places the labels of boxes and ellipses as if it were not there.)

The maze is an image under the scene, one pixel per cell: walls dark, floor light, the same in the
viewer's light and dark themes. A legend of coloured markers stands beside it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

Color = tuple[int, ...]

WALL = (58, 64, 78)
FLOOR = (236, 234, 226)
# One palette for every recording, chosen to read on the light floor and, as label text, on the
# label boxes of both themes. Red / green / blue follow the paper's figures 4 and 10.
PATH = (205, 35, 35)  # what really happened: executed path, real rollouts (red)
PLAN = (20, 150, 60)  # the TAWM's predictions: planned skill ends (green dots)
SINGLE = (40, 90, 220)  # the single-step model's predictions (blue)
LLP_PLAN = (235, 70, 190)  # LLP's predicted low-level path (fig. 10's pink lines)
WAYPOINT = (0, 170, 200)  # deploy.subgoals: the waypoint a plan aimed at (teal)
START = (40, 110, 235)
GOAL = (200, 30, 170)
AGENT = (255, 160, 0)
OUTLINE = (20, 20, 20)
SUCCESS = (20, 150, 60)
FAILURE = (215, 40, 40)

# Draw order (higher on top): the map under everything, the goal region above the agent.
ORDER_MAP = -100.0
ORDER_TRACE = 10.0
ORDER_PLAN = 20.0
ORDER_MARKER = 30.0
ORDER_AGENT = 40.0
ORDER_GOAL = 50.0


def faded(color: Color, keep: float = 0.35) -> Color:
    """`color` mixed into the floor colour (Rerun draws translucent points dark: blend instead)."""
    return tuple(round(keep * c + (1 - keep) * f) for c, f in zip(color[:3], FLOOR, strict=True))


def text_color(color: Color) -> Color:
    """A label colour that reads on the label boxes of both themes: pale colours darkened."""
    if 0.299 * color[0] + 0.587 * color[1] + 0.114 * color[2] < 150:
        return tuple(color[:3])
    return tuple(round(0.6 * c) for c in color[:3])


def unit(layout: dict[str, Any]) -> float:
    """The size of a maze cell: marker sizes are given for PointMaze's 1 m cells and scale with
    it (OGBench's ant mazes have 4 m cells)."""
    return float(layout.get("maze_size_scaling", 1.0))


def to_view(xy: Any) -> np.ndarray:
    """World positions `[..., 2]` (x right, y up) -> Rerun 2D view positions (y down)."""
    return np.asarray(xy, dtype=np.float64)[..., :2] * np.array([1.0, -1.0])


def grid_shape(layout: dict[str, Any]) -> tuple[int, int]:
    """(rows, cols) of the maze map: the cells that tile `layout["bounds"]`."""
    xmin, xmax, ymin, ymax = layout["bounds"]
    scale = float(layout["maze_size_scaling"])
    return round((ymax - ymin) / scale), round((xmax - xmin) / scale)


def maze_image(layout: dict[str, Any]) -> np.ndarray:
    """The maze map `[rows, cols, 3]` uint8, row 0 at the top (the layout's `wall_cells`)."""
    image = np.empty((*grid_shape(layout), 3), dtype=np.uint8)
    image[:] = FLOOR
    for row, col in np.asarray(layout["wall_cells"], dtype=int).reshape(-1, 2):
        image[row, col] = WALL
    return image


def log_maze(rec: rr.RecordingStream, layout: dict[str, Any], entity: str = "maze") -> None:
    """Log the map image under `entity/walls` (static, below everything), placed so that pixel
    (col, row) covers the view positions of cell (row, col)."""
    scale = float(layout["maze_size_scaling"])
    corner = to_view([-layout["x_map_center"], layout["y_map_center"]])  # the top-left corner
    rec.log(
        f"{entity}/walls",
        rr.Transform3D(translation=[*corner, 0.0], scale=[scale, scale, 1.0]),
        rr.Image(maze_image(layout), draw_order=ORDER_MAP, magnification_filter="Nearest"),
        static=True,
    )


def legend_width(layout: dict[str, Any]) -> float:
    """World width of the legend column beside the maze."""
    xmin, xmax, ymin, ymax = layout["bounds"]
    return 0.3 * max(xmax - xmin, ymax - ymin)


def map_bounds(layout: dict[str, Any], legend: bool = False) -> rrb.VisualBounds2D:
    """The maze (and the legend column when `legend`) with a small margin, in view coordinates."""
    xmin, xmax, ymin, ymax = layout["bounds"]
    margin = 0.02 * max(xmax - xmin, ymax - ymin)
    right = xmax + (legend_width(layout) if legend else 0.0)
    return rrb.VisualBounds2D(
        x_range=[xmin - margin, right + margin], y_range=[-ymax - margin, -ymin + margin]
    )


def map_view(
    layout: dict[str, Any],
    name: str,
    contents: Sequence[str],
    legend: bool = True,
    hidden: Sequence[str] = (),
) -> rrb.Spatial2DView:
    """A 2D view of the maze and `contents` (entity path expressions), bounds fixed to the maze,
    with the `/legend/**` column beside it when `legend`; the `hidden` entities start switched
    off (the blueprint panel's eye icon shows them)."""
    return rrb.Spatial2DView(
        name=name,
        origin="/",
        contents=["/maze/**", *contents, *(["/legend/**"] if legend else [])],
        visual_bounds=map_bounds(layout, legend),
        overrides={path: rrb.EntityBehavior(visible=False) for path in hidden},
    )


Marker = Literal["dot", "line", "ring", "cross"]


def cross(centers: Any, size: float) -> np.ndarray:
    """Two strokes per centre `[2 K, 2, 2]`: an x mark of half-width `size` (view coordinates)."""
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 1, 2)
    d = np.array([[-size, -size], [size, size]])
    return np.concatenate([c + d, c + d * [1, -1]])


def log_legend(
    rec: rr.RecordingStream,
    layout: dict[str, Any],
    items: Sequence[tuple[str, Color, Marker]],
    entity: str = "legend",
) -> None:
    """A column of markers with their labels beside the maze (static), one entity `entity/<k>`
    each: `(label, colour, marker)` with marker "dot", "line", "ring" or "cross". The label is a
    point of its own below the marker (Rerun centres a label on its point)."""
    xmin, xmax, ymin, ymax = layout["bounds"]
    size = max(xmax - xmin, ymax - ymin)
    x = xmax + legend_width(layout) / 2
    step = min(size / (len(items) + 0.5), size / 7)
    r = 0.02 * size
    for k, (label, color, marker) in enumerate(items):
        at = np.array([x, -ymax + step * (k + 0.35)])
        if marker == "dot":
            item: Any = rr.Points2D([at], radii=r, colors=color)
        elif marker == "ring":
            item = rr.Ellipses2D(centers=[at], half_sizes=[[r * 1.5] * 2], colors=color,
                                 line_radii=0.2 * r)  # fmt: skip
        elif marker == "cross":
            item = rr.LineStrips2D(cross([at], r), colors=color, radii=0.25 * r)
        else:
            item = rr.LineStrips2D([[at - [2.5 * r, 0], at + [2.5 * r, 0]]], colors=color,
                                   radii=0.25 * r)  # fmt: skip
        rec.log(f"{entity}/{k}", item, static=True)
        rec.log(
            f"{entity}/{k}/label",
            rr.Points2D([at + [0, 2.2 * r]], radii=1e-4, colors=text_color(color), labels=label,
                        show_labels=True),
            static=True,
        )  # fmt: skip
