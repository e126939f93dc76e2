"""Metrics of open-loop validation: position error, Gaussian NLL, calibration, wall crossings.

Pure functions on arrays, so each is testable on synthetic inputs.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from pipeline.model.skill_model import diag_normal

# Two-sided standard normal mass within k sigma: erf(k / sqrt 2).
EXPECTED_WITHIN = {k: math.erf(k / math.sqrt(2)) for k in (1, 2)}


def position_error(pred: np.ndarray, real: np.ndarray) -> np.ndarray:
    """Euclidean distance of `pred [..., 2]` from `real [..., 2]` -> `[...]`."""
    return np.linalg.norm(pred - real, axis=-1)


def gaussian_nll(x: torch.Tensor, mean: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """-log N(x; mean, diag(std^2)) `[...]`, summed over the last dimension (nats)."""
    return -diag_normal(mean, std).log_prob(x)


def within_sigma(x: np.ndarray, mean: np.ndarray, std: np.ndarray, k: float) -> np.ndarray:
    """Per dimension `[D]`: fraction of `x [N, D]` with |x - mean| <= k std.

    A calibrated Gaussian gets erf(k / sqrt 2): 68.3 % at 1 sigma, 95.4 % at 2 sigma. Less means
    the model is overconfident (its std too small), more that it is underconfident.
    """
    return (np.abs(x - mean) <= k * std).mean(axis=0)


def wall_rects(layout: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Lower-left and upper-right corners `[W, 2]` of the wall cells of a `maze_layout` dict.

    Cell (row, col) spans x in [col s - x_c, (col + 1) s - x_c], y in [y_c - (row + 1) s,
    y_c - row s] (gymnasium-robotics' convention; `pipeline.envs.maze.layout_cell` inverts it).
    """
    s = float(layout["maze_size_scaling"])
    rows, cols = np.asarray(layout["wall_cells"], dtype=np.float64).reshape(-1, 2).T
    lo = np.stack([cols * s - layout["x_map_center"], layout["y_map_center"] - (rows + 1) * s], 1)
    return lo, lo + s


def segments_hit_rects(p0: np.ndarray, p1: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Whether each segment p0 -> p1 `[N, 2]` meets any closed rectangle `[W, 2]` -> `[N]` bool.

    The slab test (Kay & Kajiya): the segment p0 + t (p1 - p0), t in [0, 1], meets a box iff the
    t-intervals where it lies within each axis' slab overlap inside [0, 1]. Hand-written because
    no geometry library is a dependency and this is ten vectorized lines.
    """
    d = (p1 - p0)[:, None, :]  # [N, 1, 2]
    a = p0[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo[None] - a) / d, (hi[None] - a) / d  # [N, W, 2]
    parallel = d == 0
    inside = (a >= lo[None]) & (a <= hi[None])
    t_enter = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    t_exit = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    enter, exit_ = t_enter.max(-1), t_exit.min(-1)  # [N, W]
    return ((enter <= exit_) & (exit_ >= 0) & (enter <= 1)).any(-1)


def first_wall_crossing(paths: np.ndarray, layout: dict[str, Any], chunk: int = 64) -> np.ndarray:
    """Index of the first step whose path segment enters a wall cell, per path.

    Args:
        paths: `[B, T + 1, 2]` x, y positions.

    Returns:
        `[B]` int: t such that segment (t - 1 -> t) is the first to meet a wall (so position t
        is reached by passing through one), or T + 1 if the path stays in free space.

    The test uses the wall cells themselves, not cells grown by the ball's radius: a real
    trajectory may touch a wall, but its centre never enters one, so any entry is physically
    impossible (a real rollout gets none: the validate stage reports that as a check).
    """
    lo, hi = wall_rects(layout)
    b, n, _ = paths.shape
    out = np.full(b, n, dtype=np.int64)
    for start in range(0, b, chunk):
        part = paths[start : start + chunk]
        p0 = part[:, :-1].reshape(-1, 2)
        p1 = part[:, 1:].reshape(-1, 2)
        hit = segments_hit_rects(p0, p1, lo, hi).reshape(len(part), n - 1)
        out[start : start + chunk] = np.where(hit.any(1), hit.argmax(1) + 1, n)
    return out


def points_in_walls(points: np.ndarray, layout: dict[str, Any]) -> np.ndarray:
    """Whether each point `[..., 2]` lies in a wall cell or outside the map -> `[...]` bool."""
    lo, hi = wall_rects(layout)
    p = points[..., None, :]
    in_wall = ((p >= lo) & (p <= hi)).all(-1).any(-1)
    xmin, xmax, ymin, ymax = layout["bounds"]
    x, y = points[..., 0], points[..., 1]
    return in_wall | (x < xmin) | (x > xmax) | (y < ymin) | (y > ymax)


def summary(values: np.ndarray) -> dict[str, float]:
    """Mean and median of a 1-D array, as plain floats."""
    return {"mean": float(np.mean(values)), "median": float(np.median(values))}
