"""Validation against recorded data alone: the TAWM vs held-out windows, no simulator needed.

Paper §4.1 asks whether the TAWM predicts where a skill ends, one skill ahead and chained over
several. A simulator is needed only to execute *new* skills; for the skills that produced the
held-out recordings the answer is in the data. So, for a dataset from any robot:

1. Draw N held-out start states from test-split episodes (`choose_starts`, the same starts as the
   simulator's validation with the same seed), each followed by L recorded windows of H steps.
2. Infer the skill of each of the L windows with the posterior: z_k = E q_phi(z | tau_k).
3. Chain the TAWM open loop from the recorded s_0 through z_1..z_k (means, and the
   moment-matched predictive distribution through particles) and compare with the recorded
   state at step k H; beside it the single-step model rolled over the recorded actions, and no
   model (the state stays s_0).

Errors are per state dimension in the dataset's own units, overall in the train split's std
units (so joints, metres and grippers weigh alike), and as a distance over the position dims
when the dataset names them; calibration is the fraction of recorded outcomes within 1 and 2
predicted sigmas. Everything is batched over the starts: one pass per skill (TAWM) or step
(single-step model), never one per window.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from pipeline.evaluation.open_loop import (
    choose_starts,
    posterior_skills,
    tawm_predictive,
)
from pipeline.evaluation.open_loop_metrics import EXPECTED_WITHIN, gaussian_nll, within_sigma
from pipeline.model.dynamics import DynamicsModel
from pipeline.model.rollout import rollout_skills
from pipeline.model.skill_model import SkillModel
from pipeline.segments import Segments

MODELS = ("tawm", "single_step", "no_model")
# The segments floor a constant dim's train std at 1e-6: in those units a model's round-off on a
# dim that never moves (a fixed height, a locked joint) would swamp the norm error, so it leaves
# them out (their errors stay in the per-dim metrics).
CONSTANT_STD = 1.5e-6
# A position is a dim named x, y or z, alone or after a prefix that says position (`pos_x`,
# `ee.position.y`, `eef_pos_z`); velocities (`vx`, `vel_x`) and joints are not positions.
_AXIS = re.compile(r"^(?P<prefix>.*?)[._\- ]?(?P<axis>[xyz])$", re.IGNORECASE)


@dataclass
class RecordedResult:
    """Predictions along N held-out recorded chains of L windows of H steps (raw units).

    Attributes:
        horizon: H, steps per skill.
        starts: `[N]` global step indices of the start states in the segments.
        recorded: `[N, L H + 1, sd]` the recorded states from each start.
        z: `[N, L, z_dim]` posterior-mean skills of the L recorded windows.
        tawm_mean: `[N, L, sd]` the TAWM's chained means after 1..L skills.
        pred_mean, pred_std: `[N, L, sd]` its moment-matched predictive distribution.
        single_step: `[N, L H + 1, sd]` the single-step model's mean rollout over the recorded
            actions.
    """

    horizon: int
    starts: np.ndarray
    recorded: np.ndarray
    z: np.ndarray
    tawm_mean: np.ndarray
    pred_mean: np.ndarray
    pred_std: np.ndarray
    single_step: np.ndarray

    @property
    def skills(self) -> int:
        """L, skills per chain."""
        return self.tawm_mean.shape[1]

    def predicted(self, model: str, k: int) -> np.ndarray:
        """`[N, sd]` where `model` ("tawm", "single_step", "no_model") puts s_{kH}."""
        if model == "tawm":
            return self.tawm_mean[:, k - 1]
        if model == "single_step":
            return self.single_step[:, k * self.horizon]
        return self.recorded[:, 0]


def position_dims(state_names: list[str]) -> list[int]:
    """The state dims of a position the dataset names: `[x, y]` or `[x, y, z]` indices, or [].

    The first group (in state order) of dims named `x`, `y` (and `z`) with the same prefix, the
    prefix empty or ending in `pos` / `position`; other names give none.
    """
    groups: dict[str, dict[str, int]] = {}
    for i, name in enumerate(state_names):
        m = _AXIS.match(name.strip())
        if m is None:
            continue
        prefix = m["prefix"].lower()
        if prefix and not prefix.endswith(("pos", "position")):
            continue
        groups.setdefault(prefix, {}).setdefault(m["axis"].lower(), i)
    for axes in groups.values():
        if "x" in axes and "y" in axes:
            return [axes[a] for a in "xyz" if a in axes]
    return []


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().numpy().astype(np.float64)


@torch.no_grad()
def run_recorded(
    model: SkillModel,
    dynamics: DynamicsModel,
    segments: Segments,
    horizon: int,
    n_starts: int,
    n_skills: int,
    particles: int,
    seed: int,
    device: torch.device,
    starts: np.ndarray | None = None,
) -> RecordedResult:
    """Both models' predictions along held-out recorded chains (module docstring).

    Args:
        horizon: H, the skill model's T.
        n_starts, n_skills: N (at most) starts and L skills per chain.
        particles: Samples propagating the TAWM's uncertainty along a chain.
        seed: Seed of the start choice and the particles.
        starts: `[N]` global start steps to use instead of drawing them (each followed by
            `n_skills * horizon` steps of its episode).

    Raises:
        UserError: no test split, or test episodes shorter than L H + 1 steps.
    """
    span = n_skills * horizon
    if starts is None:
        starts = choose_starts(segments, n_starts, span, seed)
    steps = starts[:, None] + np.arange(span + 1)
    states = torch.as_tensor(segments.states[steps], device=device)  # [N, L H + 1, sd]
    actions = torch.as_tensor(segments.actions[steps[:, :-1]], device=device)
    z = posterior_skills(model, states, actions, horizon)
    s0 = states[:, 0]
    chain = rollout_skills(model, s0, z=z)
    generator = torch.Generator().manual_seed(seed)
    pred_mean, pred_std = tawm_predictive(model, s0, z, particles, generator)
    single = dynamics.rollout(s0, actions)
    return RecordedResult(
        horizon=horizon,
        starts=starts,
        recorded=_np(states),
        z=_np(z),
        tawm_mean=_np(chain.states[:, 1:]),
        pred_mean=_np(pred_mean),
        pred_std=_np(pred_std),
        single_step=_np(single),
    )


def _stats(prefix: str, err: np.ndarray) -> dict[str, float]:
    return {f"{prefix}_mean": float(np.mean(err)), f"{prefix}_median": float(np.median(err))}


def _named(names: list[str], values: np.ndarray) -> dict[str, float]:
    return {n: float(v) for n, v in zip(names, values, strict=True)}


def skill_metrics(
    r: RecordedResult,
    k: int,
    state_names: list[str],
    std: np.ndarray,
    mean: np.ndarray,
    pos: list[int],
) -> dict[str, Any]:
    """Metrics after k recorded skills (t = k H); see `recorded_report`.

    Args:
        std, mean: `[sd]` the train split's state std and mean (the models' normalization).
        pos: Position dims (empty: no position error).
    """
    t = k * r.horizon
    real = r.recorded[:, t]
    varying = std > CONSTANT_STD
    if not varying.any():
        varying[:] = True
    out: dict[str, Any] = {"steps": t}
    for name in MODELS:
        diff = r.predicted(name, k) - real  # [N, sd]
        if pos:
            out |= _stats(f"{name}_error", np.linalg.norm(diff[:, pos], axis=-1))
        scaled = (diff / std)[:, varying]
        out |= _stats(f"{name}_norm_error", np.sqrt(np.mean(scaled**2, axis=-1)))
        out[f"{name}_error_per_dim"] = _named(state_names, np.abs(diff).mean(0))
    p_mean, p_std = r.pred_mean[:, k - 1], r.pred_std[:, k - 1]
    nll = gaussian_nll(
        *(torch.as_tensor(x) for x in ((real - mean) / std, (p_mean - mean) / std, p_std / std))
    )
    out["tawm_nll"] = float(nll.mean())
    out["tawm_sigma_per_dim"] = _named(state_names, p_std.mean(0))
    for n_sigma in EXPECTED_WITHIN:
        frac = within_sigma(real, p_mean, p_std, n_sigma)
        out[f"tawm_within_{n_sigma}sigma"] = float(frac.mean())
        out[f"tawm_within_{n_sigma}sigma_per_dim"] = _named(state_names, frac.round(4))
    return out


def recorded_report(
    r: RecordedResult,
    state_names: list[str],
    state_units: list[str],
    norm: tuple[np.ndarray, np.ndarray],
    pos: list[int],
) -> dict[str, Any]:
    """The data-only report: `starts`, `skill_horizon`, `position_dims` (names), `state_units`,
    and per horizon k = 1..L (`skills_<k>`), for `tawm` (chained TAWM means), `single_step`
    (rolled over the recorded actions) and `no_model` (s_0), each against the recorded s_{kH}:

    - `<model>_error_{mean,median}`: distance over the position dims (dataset units; only when
      the dataset names a position), as the simulator's validation measures position error;
    - `<model>_norm_error_{mean,median}`: root mean square over the dims of the error in units
      of the train split's std per dim (0: exact; about 1.4 for two unrelated states), dims
      constant in the train split left out;
    - `<model>_error_per_dim`: mean absolute error per state dim, dataset units;
    - `tawm_nll` (nats, train-normalized units as train's `val/st_nll`), `tawm_sigma_per_dim`
      (mean predicted std, dataset units), `tawm_within_{1,2}sigma` (+ `_per_dim`): the fraction
      of recorded outcomes within 1 / 2 predicted sigmas, ideally 0.683 / 0.954.

    Args:
        norm: The models' state mean and std `[sd]` (train split).
        pos: Position dims (`position_dims`, or the simulator's goal dims).
    """
    mean, std = (np.asarray(x, dtype=np.float64) for x in norm)
    report: dict[str, Any] = {
        "starts": len(r.starts),
        "skill_horizon": r.horizon,
        "position_dims": [state_names[i] for i in pos],
        "state_units": _named_units(state_names, state_units),
    }
    for k in range(1, r.skills + 1):
        report[f"skills_{k}"] = skill_metrics(r, k, state_names, std, mean, pos)
    return report


def _named_units(names: list[str], units: list[str]) -> dict[str, str]:
    return dict(zip(names, units, strict=True))


def horizons(report: dict[str, Any]) -> list[str]:
    """The `skills_<k>` keys of a data-only report, by k."""
    return sorted((k for k in report if k.startswith("skills_")), key=lambda k: int(k[7:]))


def error_table(report: dict[str, Any]) -> list[dict[str, Any]]:
    """Rows (skills, steps, then per model the norm error and, with positions, the position
    error) of the data-only error vs horizon plot."""
    rows = []
    for key in horizons(report):
        m = report[key]
        row: dict[str, Any] = {"skills": int(key[7:]), "steps": m["steps"]}
        for name in MODELS:
            row[f"{name}_norm_error"] = round(m[f"{name}_norm_error_mean"], 6)
        if report["position_dims"]:
            for name in MODELS:
                row[f"{name}_error"] = round(m[f"{name}_error_mean"], 6)
        row["tawm_within_1sigma"] = round(m["tawm_within_1sigma"], 4)
        row["tawm_within_2sigma"] = round(m["tawm_within_2sigma"], 4)
        rows.append(row)
    return rows


def per_dim_table(report: dict[str, Any]) -> list[dict[str, Any]]:
    """Rows (skills, dim, unit, mean absolute error per model, TAWM sigma and calibration) of the
    per-dimension plot."""
    rows = []
    units = report["state_units"]
    for key in horizons(report):
        m = report[key]
        for dim, unit in units.items():
            row: dict[str, Any] = {"skills": int(key[7:]), "dim": dim, "unit": unit}
            for name in MODELS:
                row[name] = round(m[f"{name}_error_per_dim"][dim], 6)
            row["tawm_sigma"] = round(m["tawm_sigma_per_dim"][dim], 6)
            row["tawm_within_1sigma"] = m["tawm_within_1sigma_per_dim"][dim]
            row["tawm_within_2sigma"] = m["tawm_within_2sigma_per_dim"][dim]
            rows.append(row)
    return rows


def headline(report: dict[str, Any]) -> dict[str, Any]:
    """`metrics/validate.json` keys of the data-only section, after one skill and after L:
    `recorded_<model>_norm_error_<k>`, `recorded_<model>_error_<k>` (with positions) and
    `recorded_tawm_within_1sigma_1`."""
    keys = horizons(report)
    out: dict[str, Any] = {}
    for key in dict.fromkeys([keys[0], keys[-1]] if keys else []):
        m, k = report[key], key[7:]
        for name in MODELS:
            out[f"recorded_{name}_norm_error_{k}"] = round(m[f"{name}_norm_error_mean"], 4)
            if report["position_dims"]:
                out[f"recorded_{name}_error_{k}"] = round(m[f"{name}_error_mean"], 4)
    if keys:
        out["recorded_tawm_within_1sigma_1"] = round(report[keys[0]]["tawm_within_1sigma"], 4)
    return out
