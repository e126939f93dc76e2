"""The validate experiment: the TAWM vs a single-step model against held-out open-loop rollouts.

Paper §4.1 / figure 4 / appendix D claim that a temporally abstract world model predicts where a
skill ends far better than a single-step model rolled forward, which compounds its errors and
walks through walls. `run_validation` measures that claim:

1. Draw N held-out start states from test-split episodes and restore each exactly in MuJoCo.
2. Choose a sequence of L skills per start, two ways ("modes"): sampled from the prior as a plan
   would be (`prior_skills`), or the posterior means of the L consecutive recorded windows that
   follow the start (`posterior_skills`).
3. Execute each sequence R times open loop in the simulator (`execute_skills`), H = T steps per
   skill.
4. Predict the end of every skill with the TAWM (chained means, and the moment-matched
   predictive distribution) and with the single-step model rolled forward H k steps under the
   actions the policy really sent.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from pipeline.dataset import DatasetInfo
from pipeline.errors import UserError
from pipeline.evaluation.open_loop import (
    BatchSim,
    choose_starts,
    execute_skills,
    posterior_skills,
    prior_skills,
    tawm_chain,
    tawm_predictive,
)
from pipeline.evaluation.validate_metrics import (
    EXPECTED_WITHIN,
    first_wall_crossing,
    gaussian_nll,
    points_in_walls,
    position_error,
    summary,
    within_sigma,
)
from pipeline.model.dynamics import DynamicsModel
from pipeline.model.skill_model import SkillModel
from pipeline.segments import Segments

MODES = ("prior", "posterior")


@dataclass(frozen=True)
class ValidationConfig:
    """What to roll out (the `validate` section of params.yaml).

    Attributes:
        starts: Held-out start states N (fewer if the test split has fewer).
        skills: Skills per open-loop sequence, L (horizons 1..L skills are reported).
        repeats: Executions R of each sequence (the action noise differs).
        sample_actions: Sample a ~ pi_theta (the demonstrator was noisy) or use its mean.
        particles: Samples that propagate the TAWM's uncertainty along a chain.
        seed: Seed of the start choice, prior skills, action noise and particles.
    """

    starts: int = 100
    skills: int = 5
    repeats: int = 4
    sample_actions: bool = True
    particles: int = 64
    seed: int = 0


@dataclass
class ModeResult:
    """Rollouts and predictions of one mode, B = N R rollouts (start-major, repeats inner).

    Attributes:
        real: `[B, L H + 1, sd]` simulated states.
        actions: `[B, L H, ad]` executed actions.
        tawm_mean: `[B, L, sd]` chained TAWM means after 1..L skills.
        pred_mean, pred_std: `[B, L, sd]` the TAWM's moment-matched predictive distribution.
        single_step: `[B, L H + 1, sd]` single-step model's mean rollout.
    """

    real: np.ndarray
    actions: np.ndarray
    tawm_mean: np.ndarray
    pred_mean: np.ndarray
    pred_std: np.ndarray
    single_step: np.ndarray


@dataclass
class Validation:
    """Everything `run_validation` produced.

    Attributes:
        horizon: H, steps per skill.
        starts: `[N]` global step indices of the start states in the segments.
        repeats: R.
        modes: "prior" / "posterior" -> results.
        sim_steps: Simulator steps taken in total.
        sim_s: Seconds spent executing rollouts (simulator + policy).
    """

    horizon: int
    starts: np.ndarray
    repeats: int
    modes: dict[str, ModeResult]
    sim_steps: int
    sim_s: float


def check_same_environment(data: DatasetInfo, checkpoint: dict[str, Any], what: str) -> None:
    """Raise `UserError` unless a checkpoint's config (`info`: the dataset it was trained on)
    describes the same environment, maze and state/action spaces as the dataset `data`."""
    info = checkpoint.get("info")
    if not isinstance(info, dict):
        raise UserError(f"{what} does not say which dataset it was trained on; retrain it")
    theirs = (info.get("env_id"), (info.get("env_kwargs") or {}).get("maze_map"))
    ours = (data.env_id, data.env_kwargs.get("maze_map"))
    if theirs[0] != ours[0]:
        raise UserError(
            f"{what} was trained on {theirs[0]!r} (dataset '{info.get('name')}'), but dataset "
            f"'{data.name}' is {ours[0]!r}; retrain it on this dataset or validate on its own"
        )
    if theirs[1] != ours[1]:
        raise UserError(f"{what} was trained on another maze map than dataset '{data.name}'")
    for key in ("state_names", "action_names"):
        if info.get(key) != getattr(data, key):
            raise UserError(
                f"{what} has {key} {info.get(key)}, dataset '{data.name}' has "
                f"{getattr(data, key)}; retrain it on this dataset"
            )


def _labels(segments: Segments, steps: np.ndarray) -> list[str]:
    """'test episode <source index>, step <t>' for global step indices (error messages)."""
    ep = np.searchsorted(segments.episode_offsets, steps, side="right") - 1
    return [
        f"test episode {segments.episode_index[e]}, step {s - segments.episode_offsets[e]}"
        for e, s in zip(ep, steps, strict=True)
    ]


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().numpy().astype(np.float64)


def run_validation(
    model: SkillModel,
    dynamics: DynamicsModel,
    segments: Segments,
    horizon: int,
    cfg: ValidationConfig,
    device: torch.device,
) -> Validation:
    """Open-loop rollouts from held-out states and both models' predictions (see module doc).

    Raises:
        UserError: no test split, test episodes too short, or unrestorable MuJoCo states.
    """
    if segments.physics is None:
        raise UserError(
            f"dataset '{segments.info.name}' has no MuJoCo states to restore; validate needs a "
            "dataset recorded in simulation"
        )
    span = cfg.skills * horizon
    starts = choose_starts(segments, cfg.starts, span, cfg.seed)
    steps = starts[:, None] + np.arange(span + 1)
    rec_states = torch.as_tensor(segments.states[steps], device=device)
    rec_actions = torch.as_tensor(segments.actions[steps[:, :-1]], device=device)
    physics = np.repeat(segments.physics[starts], cfg.repeats, axis=0)
    observed = np.repeat(segments.states[starts], cfg.repeats, axis=0)
    labels = _labels(segments, np.repeat(starts, cfg.repeats))
    sim = BatchSim(segments.info.env_id, segments.info.env_kwargs, len(physics))

    def rep(x: torch.Tensor) -> torch.Tensor:
        return x.repeat_interleave(cfg.repeats, dim=0)

    modes, sim_s = {}, 0.0
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)  # the policy's action noise (SkillModel.act)
        generator = torch.Generator().manual_seed(cfg.seed)
        for mode in MODES:
            sim.restore(physics, observed, labels)
            s0 = torch.as_tensor(sim.observe()[:: cfg.repeats], dtype=torch.float32, device=device)
            if mode == "prior":
                eps = torch.randn(len(s0), cfg.skills, model.config.z_dim, generator=generator)
                z = prior_skills(model, s0, eps.to(device))
            else:
                z = posterior_skills(model, rec_states, rec_actions, horizon)
            started = time.monotonic()
            executed = execute_skills(model, sim, rep(z), horizon, cfg.sample_actions)
            sim_s += time.monotonic() - started
            chained, _ = tawm_chain(model, s0, z)
            pred_mean, pred_std = tawm_predictive(model, s0, z, cfg.particles, generator)
            actions = torch.as_tensor(executed.actions, dtype=torch.float32, device=device)
            single = dynamics.rollout(rep(s0), actions)
            modes[mode] = ModeResult(
                real=executed.states,
                actions=executed.actions,
                tawm_mean=_np(rep(chained)),
                pred_mean=_np(rep(pred_mean)),
                pred_std=_np(rep(pred_std)),
                single_step=_np(single),
            )
    return Validation(
        horizon=horizon,
        starts=starts,
        repeats=cfg.repeats,
        modes=modes,
        sim_steps=len(MODES) * len(physics) * span,
        sim_s=sim_s,
    )


def position_dims(state_names: list[str]) -> list[int]:
    """Indices of x and y in the state (the maze plane)."""
    return [state_names.index("x"), state_names.index("y")]


def horizon_metrics(
    result: ModeResult,
    k: int,
    horizon: int,
    pos: list[int],
    state_names: list[str],
    norm: tuple[np.ndarray, np.ndarray],
    crossing: np.ndarray,
    layout: dict[str, Any],
) -> dict[str, Any]:
    """Metrics after k skills (t = k H steps) of one mode; see `validation_metrics`."""
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
    out["tawm_nll"] = float(nll.mean())
    for n_sigma in EXPECTED_WITHIN:
        frac = within_sigma(real, mean, std, n_sigma)
        out[f"tawm_within_{n_sigma}sigma"] = float(frac.mean())
        out[f"tawm_within_{n_sigma}sigma_per_dim"] = dict(
            zip(state_names, frac.round(4).tolist(), strict=True)
        )
    out["single_step_wall_crossing"] = float((crossing <= t).mean())
    out["tawm_end_in_wall"] = float(points_in_walls(result.tawm_mean[:, k - 1, pos], layout).mean())
    return out


def validation_metrics(
    v: Validation, state_names: list[str], norm: tuple[np.ndarray, np.ndarray], layout: dict
) -> dict[str, Any]:
    """The report: per mode and per horizon k = 1..L skills (key `skills_<k>`):

    - `{tawm,single_step,no_model}_error_{mean,median}`: distance (m) in the maze plane from
      the real state after k skills to the TAWM's chained mean, to the single-step model's
      rollout, and to s_0 (the no-model baseline: predict that nothing moves);
    - `tawm_nll`: -log of the real state under the TAWM's predictive Gaussian (nats, in the
      train-normalized state units of train's `val/st_nll`);
    - `tawm_within_{1,2}sigma` (+ `_per_dim`): calibration, ideally 0.683 / 0.954;
    - `single_step_wall_crossing`: fraction of single-step rollouts whose path entered a wall
      cell within these k H steps; `tawm_end_in_wall`: TAWM chained means inside a wall.

    Plus `real_wall_crossing` (a check of the wall test: real paths never enter walls).
    """
    pos = position_dims(state_names)
    report: dict[str, Any] = {
        "skill_horizon": v.horizon,
        "starts": len(v.starts),
        "rollouts_per_mode": len(v.starts) * v.repeats,
        "expected_within": {f"{k}sigma": round(p, 4) for k, p in EXPECTED_WITHIN.items()},
    }
    real_crossing = []
    for mode, result in v.modes.items():
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
    report["real_wall_crossing"] = float(np.concatenate(real_crossing).mean())
    report["timing"] = {
        "sim_steps": v.sim_steps,
        "sim_steps_per_s": v.sim_steps / max(v.sim_s, 1e-9),
    }
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


def end_position_table(v: Validation, state_names: list[str]) -> list[dict[str, Any]]:
    """Rows (mode, skills, real x/y, TAWM x/y, single-step x/y) for the predicted-vs-real plot,
    after one skill (the TAWM's own horizon) and after the whole chain of L."""
    pos = position_dims(state_names)
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
