"""Open-loop skill execution in the real simulator, from exactly restored held-out states.

The paper's §4.1 / figure 4 experiment: fix a sequence of skills z_1..z_L before acting, run the
low-level policy pi_theta(a | s, z_k) for H steps per skill in MuJoCo without replanning, and
compare where the agent really ends up with (a) the TAWM's chained prediction
p_psi(s_T | s_0, z) (eq. 1's world model) and (b) a single-step model rolled forward under the
same executed actions. Everything is batched: B simulators step together, the policy and the
models see `[B, ...]` tensors.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import torch

from pipeline.envs.maze import PHYSICS_SPEC, make_maze_env, point_env, step_point_mass
from pipeline.errors import UserError
from pipeline.model.skill_model import SkillModel
from pipeline.segments import Segments

# A restored state's qpos/qvel must reproduce the recorded observation. Observations are stored
# as float32 in the segments, so they agree with the float64 physics to float32 rounding:
# relative 6e-8; 1e-6 (plus an absolute 1e-6 near zero) leaves margin and nothing more.
_RESTORE_RTOL = 1e-6


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


class BatchSim:
    """B independent PointMaze point masses sharing one MuJoCo model.

    Each is stepped with `step_point_mass`, i.e. exactly gymnasium-robotics' `PointEnv.step`.
    A plain Python loop over the B `MjData` per step: one point mass step costs microseconds, so
    the loop (measured ~60k steps/s on one loaded core) is not worth threads.
    """

    def __init__(self, env_id: str, env_kwargs: dict, n: int):
        env = make_maze_env(env_id, **env_kwargs)
        self.model = point_env(env).model
        self.datas = [mujoco.MjData(self.model) for _ in range(n)]
        self.physics_dim = mujoco.mj_stateSize(self.model, PHYSICS_SPEC)
        env.close()

    def __len__(self) -> int:
        return len(self.datas)

    def restore(self, physics: np.ndarray, observed: np.ndarray, where: list[str]) -> None:
        """Set each simulator to a recorded full-physics state and check it took.

        As `pipeline.envs.set_physics_state`: `mj_setState`, zero solver warm start (not part
        of the state), `mj_forward`.

        Args:
            physics: `[B, physics_dim]` float64 `mjSTATE_FULLPHYSICS` states.
            observed: `[B, state_dim]` the observations recorded with them.
            where: B labels for error messages (e.g. "test episode 12, step 40").

        Raises:
            UserError: a state of the wrong size, not finite, or that does not reproduce its
                recorded observation (physics and observations from different runs).
        """
        physics = np.asarray(physics, dtype=np.float64)
        if physics.shape != (len(self), self.physics_dim):
            raise UserError(
                f"physics states have shape {physics.shape}; this environment's MuJoCo state "
                f"has {self.physics_dim} numbers; the dataset was recorded in another model"
            )
        bad = ~np.isfinite(physics).all(axis=1)
        if bad.any():
            raise UserError(f"MuJoCo state at {where[int(np.argmax(bad))]} is not finite")
        for data, state in zip(self.datas, physics, strict=True):
            mujoco.mj_setState(self.model, data, state, PHYSICS_SPEC)
            data.qacc_warmstart[:] = 0.0
            mujoco.mj_forward(self.model, data)
        got = self.observe()
        ok = np.isclose(got, observed, rtol=_RESTORE_RTOL, atol=_RESTORE_RTOL).all(axis=1)
        if not ok.all():
            i = int(np.argmax(~ok))
            raise UserError(
                f"MuJoCo state at {where[i]} cannot be restored: it gives {got[i].round(4)}, "
                f"the recorded observation is {np.asarray(observed[i]).round(4)}"
            )

    def observe(self) -> np.ndarray:
        """Observations `[B, 4]` = `[x, y, vx, vy]` (qpos, qvel), float64."""
        return np.array([(*d.qpos, *d.qvel) for d in self.datas])

    def step(self, actions: np.ndarray) -> None:
        """Apply `actions [B, 2]` for one control step (dt = 0.01 s) in every simulator."""
        for data, action in zip(self.datas, actions.tolist(), strict=True):
            step_point_mass(self.model, data, action)


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
    """
    device = z.device
    states = [sim.observe()]
    actions = []
    for k in range(z.shape[1]):
        for _ in range(horizon):
            s = torch.as_tensor(states[-1], dtype=torch.float32, device=device)
            a = model.act(s, z[:, k], sample=sample_actions).cpu().numpy().astype(np.float64)
            sim.step(a)
            actions.append(a)
            states.append(sim.observe())
    return Executed(np.stack(states, axis=1), np.stack(actions, axis=1))


@torch.no_grad()
def prior_skills(model: SkillModel, s0: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """A skill sequence sampled from the prior, as a plan would hold it (paper §3).

    z_k = mu_omega(s_k) + sigma_omega(s_k) * eps_k with s_k the TAWM's chained mean prediction
    (s_0 is real): open loop, the real s_k is not known when the sequence is fixed.

    Args:
        s0: `[B, sd]` raw start states.
        eps: `[B, L, z_dim]` standard normal draws (whitened skills).

    Returns:
        z `[B, L, z_dim]`.
    """
    s, zs = s0, []
    for k in range(eps.shape[1]):
        mu, sigma = model.skill_prior(s)
        zs.append(mu + sigma * eps[:, k])
        s = model.predict_end(s, zs[-1])[0]
    return torch.stack(zs, dim=1)


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


@torch.no_grad()
def tawm_chain(
    model: SkillModel, s0: torch.Tensor, z: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Deterministic chained prediction: s_{k+1} = mean p_psi(s_T | s_k, z_k), from real s_0.

    This is what a planner reads off the TAWM for a skill sequence.

    Returns:
        means `[B, L, sd]` and the TAWM std at each chained step `[B, L, sd]` (raw units).
    """
    s, means, stds = s0, [], []
    for k in range(z.shape[1]):
        s, std = model.predict_end(s, z[:, k])
        means.append(s)
        stds.append(std)
    return torch.stack(means, dim=1), torch.stack(stds, dim=1)


@torch.no_grad()
def tawm_predictive(
    model: SkillModel, s0: torch.Tensor, z: torch.Tensor, particles: int, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """The TAWM's predictive distribution of s_{kH} after k chained skills, moment-matched.

    p(s_k | s_0, z_1..k) = integral of prod p_psi(s_j | s_{j-1}, z_j): propagated with
    `particles` samples per rollout; at each k the mixture of the particles' Gaussians is
    summarized by its mean and per-dimension std (exact for k = 1, where every particle is s_0).

    Args:
        s0: `[B, sd]`; z: `[B, L, z_dim]`.

    Returns:
        mean, std `[B, L, sd]` (raw units).
    """
    b, n_skills, _ = z.shape
    s = s0[:, None].expand(b, particles, -1)
    means, stds = [], []
    for k in range(n_skills):
        mu, sigma = model.predict_end(s, z[:, k, None].expand(b, particles, -1))
        mean = mu.mean(1)
        var = sigma.square().mean(1) + (mu - mean[:, None]).square().mean(1)
        means.append(mean)
        stds.append(var.sqrt())
        noise = torch.randn(mu.shape, generator=generator).to(mu.device)
        s = mu + sigma * noise
    return torch.stack(means, dim=1), torch.stack(stds, dim=1)
