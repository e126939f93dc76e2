"""Skill planning scored in the simulator: the "perfect model" rung of the manipulation ladder.

The same CEM over the same whitened skills as OPOSM's planner (`SkillPlanner`), but every
candidate is scored by executing it: the environment's exact physics state is copied into
`candidates` scratch simulators, skill k is `z_k = mu_omega(s_k) + sigma_omega(s_k) eps_k` at the
state the simulator really reached, the low-level policy pi_theta(a | s, z_k) runs it for the
skill's T steps (its mean action, closed loop on the simulated state), and the goal cost reads the
simulated states at the skills' ends instead of the TAWM's chained means.

What it measures: an agent that plans this way fails only where the skills or the cost cannot do
the task (or CEM does not find the plan); where it succeeds and OPOSM does not, the TAWM's
predictions are what stops OPOSM. It is an upper bound, not an agent: each candidate costs
`horizon x T` simulator steps (at ~700 manipulation steps/s per core, a replan of 32 candidates,
3 skills of 20 steps and 3 iterations takes ~8 s), so it runs with few candidates
(`deploy.planner.*` overrides; docs/manipulation.md). Random pushes of the deploy environment are
not simulated (the scratch simulators have none).
"""

from __future__ import annotations

import mujoco
import numpy as np
import torch

from pipeline.envs.batch import BatchSim
from pipeline.envs.spec import EnvSpec
from pipeline.errors import UserError
from pipeline.model.skill_model import SkillModel
from pipeline.planning.fused import PlannerNets
from pipeline.planning.mpc import SkillMPC
from pipeline.planning.skills import Plan, PlannerConfig, SkillPlanner


class SimulatedRollout:
    """Executes whitened skill sequences from exact physics states in `candidates` scratch
    simulators of `spec`'s environment running `mj_model` (the deploy environment's, with its
    `deploy.mass_scale`), `skill_steps` steps per skill."""

    def __init__(
        self,
        model: SkillModel,
        spec: EnvSpec,
        mj_model: mujoco.MjModel,
        candidates: int,
        skill_steps: int,
    ):
        self.model = model
        self.sim = BatchSim(spec, candidates, [mj_model] * candidates)
        self.sim.seed_slots(range(candidates))  # teleports draw from it (the OGBench mazes)
        self.skill_steps = skill_steps

    @torch.no_grad()
    def __call__(self, eps: torch.Tensor, physics: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw states `[B, K, L + 1, sd]` at the start and each skill's end (NaN from the step
        a simulator failed at: the candidate's cost is then infinite) and skills `[B, K, L, z]`,
        for `eps [B, K, L, z]` from the physics states `physics [B, physics_dim]`."""
        b, k, n_skills, z_dim = eps.shape
        if k != len(self.sim):
            raise ValueError(f"{k} candidates for {len(self.sim)} scratch simulators")
        m, device = self.model, eps.device
        states = torch.empty(b, k, n_skills + 1, m.config.state_dim, device=device)
        skills = torch.empty(b, k, n_skills, z_dim, device=device)
        for p in range(b):
            self.sim.set_state(np.repeat(physics[p][None], k, axis=0))
            failed = np.zeros(k, dtype=bool)
            s = self._observe(device)
            states[p, :, 0] = s
            for i in range(n_skills):
                mu, sigma = m.skill_prior(s)
                skills[p, :, i] = torch.addcmul(mu, sigma, eps[p, :, i])
                for _ in range(self.skill_steps):
                    actions = m.act(s, skills[p, :, i]).double().cpu().numpy()
                    failed[list(self.sim.step(actions))] = True
                    s = self._observe(device)
                states[p, :, i + 1] = s
                states[p, torch.as_tensor(failed), i + 1] = float("nan")
        return states, skills

    def _observe(self, device: torch.device) -> torch.Tensor:
        return torch.as_tensor(self.sim.observe(), dtype=torch.float32, device=device)


class SimulatorPlanner(SkillPlanner):
    """`SkillPlanner` whose rollout is `SimulatedRollout`: set `starts` (the problems' physics
    states `[B, physics_dim]`) before each `plan`. Eager only (no compile, no Triton kernel)."""

    def __init__(self, model: SkillModel, config: PlannerConfig, rollout: SimulatedRollout):
        if config.compile or config.kernel != "torch":
            raise UserError(
                "the oposm_sim agent plans in the simulator: set deploy.planner.compile=false "
                "and deploy.planner.kernel=torch"
            )
        if config.uncertainty_weight:
            raise UserError(
                "the oposm_sim agent scores plans in the simulator, which has no model "
                "uncertainty: set deploy.planner.uncertainty_weight=0"
            )
        if config.support_weight or config.data_skills:
            raise UserError(
                "the oposm_sim agent scores plans in the simulator, whose outcomes need no "
                "support in the data: set deploy.planner.support_weight=0 and data_skills=0"
            )
        if config.cem.candidates != len(rollout.sim):
            raise ValueError("one scratch simulator per CEM candidate")
        super().__init__(model, config)
        self.rollout = rollout
        self.starts: np.ndarray | None = None

    def _rollout(self, eps, nets: PlannerNets, s0, s0_n, prior0, local=None):
        """The states the simulator reaches and the skills it ran; no uncertainty term."""
        if self.starts is None or len(self.starts) != len(s0):
            raise RuntimeError("set SimulatorPlanner.starts to the problems' physics states")
        return (*self.rollout(eps, self.starts), None)


class SimulatedSkillMPC(SkillMPC):
    """`SkillMPC` with a `SimulatorPlanner`, planning from the exact physics states of the
    deploy environment's slots (`attach` it to them before the first episode)."""

    name = "oposm_sim"

    def __init__(self, model: SkillModel, planner: SimulatorPlanner, *args, **kwargs):
        super().__init__(model, planner, *args, **kwargs)
        self.planner: SimulatorPlanner = planner
        self.envs: BatchSim | None = None

    def attach(self, envs: BatchSim) -> None:
        """Plan from the physics states of `envs`' slots (the slots the episodes run in)."""
        self.envs = envs

    def replan(self, rows: np.ndarray, states: np.ndarray) -> Plan:
        if self.envs is None:
            raise RuntimeError("attach the oposm_sim agent to the deploy environment first")
        self.planner.starts = self.envs.get_state(rows)
        return super().replan(rows, states)
