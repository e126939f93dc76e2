"""Open-loop evaluation: the TAWM vs a single-step model against held-out rollouts in MuJoCo.

Paper §4.1 / figure 4 / appendix D claim that a temporally abstract world model predicts where a
skill ends far better than a single-step model rolled forward, which compounds its errors and walks
through walls. `run_open_loop` measures that claim (the `validate` stage):

1. Draw N held-out start states from test-split episodes and restore each exactly in MuJoCo.
2. Choose a sequence of L skills per start, two ways ("modes"): sampled from the prior as a plan
   would be (whitened skills through `rollout_skills`), or the posterior means of the L consecutive
   recorded windows that follow the start (`posterior_skills`).
3. Execute each sequence R times open loop in the simulator (`execute_skills`), H = T steps per
   skill: the policy pi_theta(a | s, z_k) stays closed-loop on s_t, the skills never change.
4. Predict the end of every skill with the TAWM (chained means, and the moment-matched predictive
   distribution) and with the single-step model rolled forward H k steps under the actions the
   policy really sent.

The metrics of the result are in `pipeline.evaluation.open_loop_metrics`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.config import ValidateParams
from pipeline.envs.batch import BatchSim
from pipeline.envs.disturbance import Pushes
from pipeline.envs.spec import EnvSpec
from pipeline.errors import UserError
from pipeline.model.dynamics import DynamicsModel
from pipeline.model.rollout import rollout_skills
from pipeline.model.skill_model import SkillModel
from pipeline.segments import Segments

MODES = ("prior", "posterior")

# A restored state's qpos/qvel must reproduce the recorded observation. Observations are stored
# as float32 in the segments, so they agree with the float64 physics to float32 rounding:
# relative 6e-8; 1e-6 (plus an absolute 1e-6 near zero) leaves margin and nothing more.
_RESTORE_RTOL = 1e-6


@dataclass
class ModeResult:
    """Rollouts and predictions of one mode, B = N R rollouts (start-major, repeats inner).

    Attributes:
        real: `[B, L H + 1, sd]` simulated states.
        actions: `[B, L H, ad]` executed actions.
        tawm_mean: `[B, L, sd]` chained TAWM means after 1..L skills.
        pred_mean, pred_std: `[B, L, sd]` the TAWM's moment-matched predictive distribution.
        single_step: `[B, L H + 1, sd]` single-step model's mean rollout.
        recorded: `[B, L H + 1, sd]` the recorded states the skills were inferred from (the
            posterior mode; None for the prior's skills, which no recording produced).
    """

    real: np.ndarray
    actions: np.ndarray
    tawm_mean: np.ndarray
    pred_mean: np.ndarray
    pred_std: np.ndarray
    single_step: np.ndarray
    recorded: np.ndarray | None = None


@dataclass
class OpenLoopResult:
    """Everything `run_open_loop` produced.

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


def choose_starts(segments: Segments, n: int, span: int, seed: int) -> np.ndarray:
    """Global step indices `[N]` (N <= n) of held-out start states s_0 in the test split.

    Each start leaves `span` more recorded steps in its episode (for the posterior skills of a
    chain of windows). Drawn without replacement, seeded, returned sorted.

    Raises:
        UserError: no test episodes, or none longer than `span`.
    """
    episodes = segments.episodes_in("test")
    if episodes.size == 0:
        raise UserError(
            f"dataset '{segments.info.name}' has no test split; give segment.split.test a "
            "fraction and re-run `oposm segment`"
        )
    offsets = segments.episode_offsets
    valid = [np.arange(offsets[e], offsets[e + 1] - span) for e in episodes]
    candidates = np.concatenate(valid)
    if candidates.size == 0:
        raise UserError(
            f"test episodes of '{segments.info.name}' are shorter than {span + 1} steps "
            "(validate.skills x the skill horizon); lower validate.skills"
        )
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(candidates, size=min(n, candidates.size), replace=False))


def restore(sim: BatchSim, physics: np.ndarray, observed: np.ndarray, where: list[str]) -> None:
    """Put every slot in a recorded full-physics state and check that it took.

    Args:
        physics: `[B, physics_dim]` float64 `mjSTATE_FULLPHYSICS` states.
        observed: `[B, state_dim]` the observations recorded with them.
        where: B labels for error messages (e.g. "test episode 12, step 40").

    Raises:
        UserError: a state of the wrong size, not finite, or that does not reproduce its
            recorded observation (physics and observations from different runs).
    """
    physics = np.asarray(physics, dtype=np.float64)
    if physics.shape != (len(sim), sim.physics_dim):
        raise UserError(
            f"physics states have shape {physics.shape}; this environment's MuJoCo state "
            f"has {sim.physics_dim} numbers; the dataset was recorded in another model"
        )
    bad = ~np.isfinite(physics).all(axis=1)
    if bad.any():
        raise UserError(f"MuJoCo state at {where[int(np.argmax(bad))]} is not finite")
    sim.set_state(physics)
    got = sim.observe()
    ok = np.isclose(got, observed, rtol=_RESTORE_RTOL, atol=_RESTORE_RTOL).all(axis=1)
    if not ok.all():
        i = int(np.argmax(~ok))
        raise UserError(
            f"MuJoCo state at {where[i]} cannot be restored: it gives {got[i].round(4)}, "
            f"the recorded observation is {np.asarray(observed[i]).round(4)}"
        )


@dataclass
class Executed:
    """Real open-loop executions of skill sequences.

    Attributes:
        states: `[B, L * H + 1, sd]` s_0 .. s_{LH} as simulated.
        actions: `[B, L * H, ad]` the actions the low-level policy sent.
    """

    states: np.ndarray
    actions: np.ndarray


def execute_skills(
    model: SkillModel, sim: BatchSim, z: torch.Tensor, horizon: int, sample_actions: bool
) -> Executed:
    """Run pi_theta(a_t | s_t, z_k) for `horizon` steps per skill, skills in order, open loop.

    The simulators must already hold the start states. Skill k drives steps
    `[k H, (k + 1) H)`; the skill sequence never changes in response to what happens (no
    replanning), the policy itself is closed-loop on s_t as in the paper.

    Args:
        z: `[B, L, z_dim]` skill sequence per simulator, on the model's device.
        horizon: H, steps per skill (the TAWM's T).
        sample_actions: Sample a ~ pi (as the data's noisy demonstrator did) or take its mean.

    Raises:
        UserError: a simulator failed (non-finite action or MuJoCo instability).
    """
    device = z.device
    states = [sim.observe()]
    actions = []
    for k in range(z.shape[1]):
        for _ in range(horizon):
            s = torch.as_tensor(states[-1], dtype=torch.float32, device=device)
            a = model.act(s, z[:, k], sample=sample_actions).cpu().numpy().astype(np.float64)
            if failed := sim.step(a):
                i, why = next(iter(failed.items()))
                raise UserError(f"open-loop rollout {i} failed at step {len(actions)}: {why}")
            actions.append(a)
            states.append(sim.observe())
    return Executed(np.stack(states, axis=1), np.stack(actions, axis=1))


@torch.no_grad()
def posterior_skills(
    model: SkillModel, states: torch.Tensor, actions: torch.Tensor, horizon: int
) -> torch.Tensor:
    """Posterior-mean skills of consecutive held-out windows: z_k = E q_phi(z | tau_k).

    Args:
        states: `[B, L * H + 1, sd]` recorded states from each start.
        actions: `[B, L * H, ad]` recorded actions.

    Returns:
        z `[B, L, z_dim]`; window k is s_{kH .. kH + H - 1}, a_{kH .. kH + H - 1}.
    """
    b, n, _ = actions.shape
    windows = n // horizon
    s = states[:, :-1].reshape(b * windows, horizon, -1)
    a = actions.reshape(b * windows, horizon, -1)
    return model.infer_skill(s, a)[0].reshape(b, windows, -1)


def tawm_predictive(
    model: SkillModel, s0: torch.Tensor, z: torch.Tensor, particles: int, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """The TAWM's predictive distribution of s_{kH} after k chained skills, moment-matched.

    p(s_k | s_0, z_1..k) = integral of prod p_psi(s_j | s_{j-1}, z_j): propagated with
    `particles` sampled chains per rollout; at each k the mixture of the particles' Gaussians is
    summarized by its mean and per-dimension std (exact for k = 1, where every particle is s_0,
    with a single-Gaussian TAWM; of a mixture TAWM each particle draws its component).

    Args:
        s0: `[B, sd]`; z: `[B, L, z_dim]`.

    Returns:
        mean, std `[B, L, sd]` (raw units).
    """
    b, n_skills, z_dim = z.shape
    chains = rollout_skills(
        model, s0[:, None], z=z[:, None].expand(b, particles, n_skills, z_dim), generator=generator
    )
    mu, sigma = chains.mean, chains.std  # [B, P, L, sd]
    mean = mu.mean(1)
    var = sigma.square().mean(1) + (mu - mean[:, None]).square().mean(1)
    return mean, var.sqrt()


def start_labels(segments: Segments, steps: np.ndarray) -> list[str]:
    """'test episode <source index>, step <t>' for global step indices (messages, titles)."""
    ep = np.searchsorted(segments.episode_offsets, steps, side="right") - 1
    return [
        f"test episode {segments.episode_index[e]}, step {s - segments.episode_offsets[e]}"
        for e, s in zip(ep, steps, strict=True)
    ]


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().numpy().astype(np.float64)


def run_open_loop(
    model: SkillModel,
    dynamics: DynamicsModel,
    segments: Segments,
    spec: EnvSpec,
    horizon: int,
    cfg: ValidateParams,
    device: torch.device,
) -> OpenLoopResult:
    """Open-loop rollouts from held-out states and both models' predictions (see module doc).

    Seeded by `cfg.seed`: start choice, prior skills, action noise and particles.

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
    labels = start_labels(segments, np.repeat(starts, cfg.repeats))
    sim = BatchSim(spec, len(physics), pushes=Pushes.of_dataset(segments.info.generator))
    push_seeds = [cfg.seed * 1_000_003 + j for j in range(len(physics))]  # same in both modes

    def rep(x: torch.Tensor) -> torch.Tensor:
        return x.repeat_interleave(cfg.repeats, dim=0)

    modes, sim_s = {}, 0.0
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)  # the policy's action noise (SkillModel.act)
        generator = torch.Generator().manual_seed(cfg.seed)
        for mode in MODES:
            restore(sim, physics, observed, labels)
            sim.seed_slots(push_seeds)
            s0 = torch.as_tensor(sim.observe()[:: cfg.repeats], dtype=torch.float32, device=device)
            if mode == "prior":
                eps = torch.randn(len(s0), cfg.skills, model.config.z_dim, generator=generator)
                chain = rollout_skills(model, s0, eps=eps.to(device))
            else:
                z = posterior_skills(model, rec_states, rec_actions, horizon)
                chain = rollout_skills(model, s0, z=z)
            started = time.monotonic()
            executed = execute_skills(model, sim, rep(chain.z), horizon, cfg.sample_actions)
            sim_s += time.monotonic() - started
            pred_mean, pred_std = tawm_predictive(model, s0, chain.z, cfg.particles, generator)
            actions = torch.as_tensor(executed.actions, dtype=torch.float32, device=device)
            single = dynamics.rollout(rep(s0), actions)
            modes[mode] = ModeResult(
                real=executed.states,
                actions=executed.actions,
                tawm_mean=_np(rep(chain.states[:, 1:])),
                pred_mean=_np(rep(pred_mean)),
                pred_std=_np(rep(pred_std)),
                single_step=_np(single),
                recorded=None if mode == "prior" else _np(rep(rec_states)),
            )
    return OpenLoopResult(
        horizon=horizon,
        starts=starts,
        repeats=cfg.repeats,
        modes=modes,
        sim_steps=len(MODES) * len(physics) * span,
        sim_s=sim_s,
    )
