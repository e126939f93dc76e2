"""Metrics of the open-loop evaluation: position error, Gaussian NLL, calibration, wall crossings,
and the `validate` report built from them (per mode and horizon).

The metric functions are pure functions on arrays, each testable on synthetic inputs.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from pipeline.envs.spec import EnvSpec
from pipeline.evaluation.open_loop import MODES, ModeResult, OpenLoopResult
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
    y_c - row s] (gymnasium-robotics' convention; `pipeline.envs.maze.env.layout_cell` inverts it).
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


def horizon_metrics(
    result: ModeResult,
    k: int,
    horizon: int,
    pos: list[int],
    state_names: list[str],
    norm: tuple[np.ndarray, np.ndarray],
    crossing: np.ndarray | None,
    layout: dict[str, Any],
) -> dict[str, Any]:
    """Metrics after k skills (t = k H steps) of one mode; see `open_loop_report` (`crossing`
    None: no walls, no wall metrics)."""
    t = k * horizon
    real = result.real[:, t]
    mean, std = result.pred_mean[:, k - 1], result.pred_std[:, k - 1]
    mu, sigma = norm
    nll = gaussian_nll(
        *(torch.as_tensor(x) for x in ((real - mu) / sigma, (mean - mu) / sigma, std / sigma))
    )
    out: dict[str, Any] = {"steps": t}
    errors = {
        "tawm": position_error(result.tawm_mean[:, k - 1, pos], real[:, pos]),
        "single_step": position_error(result.single_step[:, t, pos], real[:, pos]),
        "no_model": position_error(result.real[:, 0, pos], real[:, pos]),
    }
    for name, err in errors.items():
        stats = summary(err)
        out[f"{name}_error_mean"], out[f"{name}_error_median"] = stats["mean"], stats["median"]
    if result.recorded is not None:  # skill fidelity: does executing z replay its window?
        recorded = result.recorded[:, t, pos]
        fidelity = {
            "replay": position_error(real[:, pos], recorded),
            "tawm_recorded": position_error(result.tawm_mean[:, k - 1, pos], recorded),
            "no_model_recorded": position_error(result.real[:, 0, pos], recorded),
        }
        for name, err in fidelity.items():
            stats = summary(err)
            out[f"{name}_error_mean"], out[f"{name}_error_median"] = stats["mean"], stats["median"]
    out["tawm_nll"] = float(nll.mean())
    for n_sigma in EXPECTED_WITHIN:
        frac = within_sigma(real, mean, std, n_sigma)
        out[f"tawm_within_{n_sigma}sigma"] = float(frac.mean())
        out[f"tawm_within_{n_sigma}sigma_per_dim"] = dict(
            zip(state_names, frac.round(4).tolist(), strict=True)
        )
    if crossing is not None:
        out["single_step_wall_crossing"] = float((crossing <= t).mean())
        end = result.tawm_mean[:, k - 1, pos]
        out["tawm_end_in_wall"] = float(points_in_walls(end, layout).mean())
    return out


def has_walls(layout: dict[str, Any]) -> bool:
    """Whether a spec's layout is a maze with wall cells (not a manipulation workspace)."""
    return "wall_cells" in layout


def open_loop_report(
    v: OpenLoopResult, spec: EnvSpec, state_names: list[str], norm: tuple[np.ndarray, np.ndarray]
) -> dict[str, Any]:
    """The report: per mode and per horizon k = 1..L skills (key `skills_<k>`):

    - `{tawm,single_step,no_model}_error_{mean,median}`: distance (m) in the maze plane from
      the real state after k skills to the TAWM's chained mean, to the single-step model's
      rollout, and to s_0 (the no-model baseline: predict that nothing moves);
    - `tawm_nll`: -log of the real state under the TAWM's predictive Gaussian (nats, in the
      train-normalized state units of train's `val/st_nll`);
    - `tawm_within_{1,2}sigma` (+ `_per_dim`): calibration, ideally 0.683 / 0.954;
    - posterior mode only, skill fidelity against the recorded states the skills were inferred
      from: `replay_error_*` (executed vs recorded, after k skills), `tawm_recorded_error_*`,
      `no_model_recorded_error_*` (s_0 vs recorded); a policy that cannot replay its own
      skills (replay error near no model's) leaves a planner nothing to chain;
    - `single_step_wall_crossing`: fraction of single-step rollouts whose path entered a wall
      cell within these k H steps; `tawm_end_in_wall`: TAWM chained means inside a wall.

    Plus `real_wall_crossing` (a check of the wall test: real paths never enter walls).
    Positions are the state dims `spec.goal_dims` (OGBench's manipulation: the objects' goal
    dims, in observation units); walls come from `spec.layout`, and a layout without walls (the
    manipulation workspace) has no wall metrics.
    """
    pos, layout = list(spec.goal_dims), spec.layout
    report: dict[str, Any] = {
        "skill_horizon": v.horizon,
        "starts": len(v.starts),
        "rollouts_per_mode": len(v.starts) * v.repeats,
        "expected_within": {f"{k}sigma": round(p, 4) for k, p in EXPECTED_WITHIN.items()},
    }
    real_crossing = []
    walls = has_walls(layout)
    for mode, result in v.modes.items():
        crossing = None
        if walls:
            crossing = first_wall_crossing(result.single_step[..., pos], layout)
            real_crossing.append(
                first_wall_crossing(result.real[..., pos], layout) < result.real.shape[1]
            )
        report[mode] = {
            f"skills_{k}": horizon_metrics(
                result, k, v.horizon, pos, state_names, norm, crossing, layout
            )
            for k in range(1, result.tawm_mean.shape[1] + 1)
        }
    if walls:
        report["real_wall_crossing"] = float(np.concatenate(real_crossing).mean())
    else:  # a manipulation env: positions are its goal dims in observation units
        report["position_unit"] = "observation units"
    # Steps, not seconds: the report must be byte-identical when rerun (the stage logs the rate).
    report["timing"] = {"sim_steps": v.sim_steps}
    return report


def error_table(report: dict[str, Any]) -> list[dict[str, float]]:
    """Rows of mean position error vs horizon for the DVC plot (one row per k)."""
    rows = []
    for key, first in report[MODES[0]].items():
        row = {"skills": int(key.split("_")[1]), "steps": first["steps"]}
        for mode in MODES:
            for model in ("tawm", "single_step", "no_model"):
                row[f"{model}_{mode}"] = report[mode][key][f"{model}_error_mean"]
        rows.append(row)
    return rows


def end_position_table(v: OpenLoopResult, pos: list[int]) -> list[dict[str, Any]]:
    """Rows (mode, skills, real x/y, TAWM x/y, single-step x/y) for the predicted-vs-real plot,
    after one skill (the TAWM's own horizon) and after the whole chain of L; `pos`: the state
    dims of x and y."""
    rows = []
    for mode, r in v.modes.items():
        for k in sorted({1, r.tawm_mean.shape[1]}):
            t = k * v.horizon
            cols = (r.real[:, t, pos], r.tawm_mean[:, k - 1, pos], r.single_step[:, t, pos])
            for real, tawm, single in zip(*cols, strict=True):
                rows.append(
                    {
                        "mode": mode,
                        "skills": k,
                        "real_x": round(float(real[0]), 4),
                        "real_y": round(float(real[1]), 4),
                        "tawm_x": round(float(tawm[0]), 4),
                        "tawm_y": round(float(tawm[1]), 4),
                        "single_step_x": round(float(single[0]), 4),
                        "single_step_y": round(float(single[1]), 4),
                    }
                )
    return rows
