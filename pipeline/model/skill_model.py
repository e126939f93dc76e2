"""The OPOSM skill model (paper §2, appendix C): q_phi, p_omega, pi_theta and the TAWM p_psi.

All four are diagonal Gaussians. Networks work on states and actions normalized with the segment
stage's train statistics; the model stores those statistics as buffers, so its public methods take
and return raw environment units.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn
from torch.distributions import Independent, Normal

from pipeline.model.networks import GaussianHead, GaussianMLP


@dataclass(frozen=True)
class SkillModelConfig:
    """Everything needed to rebuild a `SkillModel` (stored as the checkpoint's config.json).

    Attributes:
        state_dim: Size of a state vector.
        action_dim: Size of an action vector.
        z_dim: Size of the skill latent z (paper: 256).
        hidden: Width of every hidden layer (paper: 256).
        tawm_shared_std: One scalar std shared by all state dims in p_psi (paper, mazes) instead
            of one per dim.
        min_std: Floor added to every softplus std.
    """

    state_dim: int
    action_dim: int
    z_dim: int = 256
    hidden: int = 256
    tawm_shared_std: bool = True
    min_std: float = 1e-4

    def to_dict(self) -> dict:
        return asdict(self)


def diag_normal(mean: torch.Tensor, std: torch.Tensor) -> Independent:
    """A diagonal Gaussian over the last dimension (log_prob sums over it).

    Argument validation is off: it costs time in the hot loop, and a NaN must reach the
    training loop's divergence check (which names the step) rather than fail inside torch.
    """
    return Independent(Normal(mean, std, validate_args=False), 1, validate_args=False)


class SkillPosterior(nn.Module):
    """q_phi(z | s_0..T-1, a_0..T-1), appendix C.1.

    States pass through Linear + ReLU; embedded states concatenated with actions feed a one-layer
    bidirectional GRU; the final hidden states of both directions feed the mean and std heads.
    """

    def __init__(self, config: SkillModelConfig):
        super().__init__()
        h = config.hidden
        self.embed = nn.Sequential(nn.Linear(config.state_dim, h), nn.ReLU())
        self.gru = nn.GRU(h + config.action_dim, h, batch_first=True, bidirectional=True)
        self.head = GaussianHead(2 * h, h, config.z_dim, min_std=config.min_std)

    def forward(self, states: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Normalized `states [B, T, sd]`, `actions [B, T, ad]` -> mean, std `[B, z_dim]`."""
        x = torch.cat([self.embed(states), actions], dim=-1)
        _, h_n = self.gru(x)  # [2, B, h]: last hidden state of the forward and backward passes
        return self.head(torch.cat([h_n[0], h_n[1]], dim=-1))


class SkillModel(nn.Module):
    """Posterior, prior, low-level policy and temporally abstract world model, with normalization.

    Parameter groups (for the EM optimizers): `posterior` (E-step) and `generative()` (M-step:
    policy, TAWM, prior).
    """

    def __init__(self, config: SkillModelConfig):
        super().__init__()
        self.config = config
        sd, ad, z, h = config.state_dim, config.action_dim, config.z_dim, config.hidden
        self.posterior = SkillPosterior(config)
        self.prior = GaussianMLP(sd, h, z, min_std=config.min_std)
        self.policy = GaussianMLP(sd + z, h, ad, min_std=config.min_std)
        self.tawm = GaussianMLP(
            sd + z, h, sd, shared_std=config.tawm_shared_std, min_std=config.min_std
        )
        self.register_buffer("state_mean", torch.zeros(sd))
        self.register_buffer("state_std", torch.ones(sd))
        self.register_buffer("action_mean", torch.zeros(ad))
        self.register_buffer("action_std", torch.ones(ad))

    def generative(self) -> list[nn.Parameter]:
        """Parameters updated by the M-step: theta (policy), psi (TAWM), omega (prior)."""
        return [*self.policy.parameters(), *self.tawm.parameters(), *self.prior.parameters()]

    def set_normalization(self, state_mean, state_std, action_mean, action_std) -> None:
        """Copy train-split statistics (array-likes) into the model's buffers."""
        for name, value in zip(
            ("state_mean", "state_std", "action_mean", "action_std"),
            (state_mean, state_std, action_mean, action_std),
            strict=True,
        ):
            buffer = getattr(self, name)
            buffer.copy_(torch.as_tensor(value, dtype=buffer.dtype))

    # -- normalization ----------------------------------------------------------------------
    def norm_states(self, s: torch.Tensor) -> torch.Tensor:
        return (s - self.state_mean) / self.state_std

    def norm_actions(self, a: torch.Tensor) -> torch.Tensor:
        return (a - self.action_mean) / self.action_std

    # -- distributions on normalized inputs (training) ---------------------------------------
    def posterior_dist(self, states_n: torch.Tensor, actions_n: torch.Tensor) -> Independent:
        """q_phi(z | tau) from normalized `states [B, T, sd]` (s_0..T-1), `actions [B, T, ad]`."""
        return diag_normal(*self.posterior(states_n, actions_n))

    def prior_dist(self, s0_n: torch.Tensor) -> Independent:
        """p_omega(z | s_0) from normalized `s0 [..., sd]`."""
        return diag_normal(*self.prior(s0_n))

    def policy_dist(self, s_n: torch.Tensor, z: torch.Tensor) -> Independent:
        """pi_theta(a | s, z) over normalized actions; `s [..., sd]`, `z [..., z]`."""
        return diag_normal(*self.policy(torch.cat([s_n, z], dim=-1)))

    def tawm_dist(self, s0_n: torch.Tensor, z: torch.Tensor) -> Independent:
        """p_psi(s_T | s_0, z) over normalized s_T; `s0 [..., sd]`, `z [..., z]`."""
        return diag_normal(*self.tawm(torch.cat([s0_n, z], dim=-1)))

    # -- raw-unit interface (planning, validation, deployment) ----------------------------------
    @torch.no_grad()
    def skill_prior(self, s0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw `s0 [..., sd]` -> prior mean, std over z `[..., z]` (for whitened planning)."""
        return self.prior(self.norm_states(s0))

    @torch.no_grad()
    def predict_end(self, s0: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw `s0 [..., sd]`, `z [..., z]` -> TAWM mean, std of s_T in raw units `[..., sd]`."""
        mean, std = self.tawm(torch.cat([self.norm_states(s0), z], dim=-1))
        return mean * self.state_std + self.state_mean, std * self.state_std

    @torch.no_grad()
    def act(self, s: torch.Tensor, z: torch.Tensor, sample: bool = False) -> torch.Tensor:
        """Raw `s [..., sd]`, `z [..., z]` -> raw action `[..., ad]` (mean, or sampled)."""
        mean, std = self.policy(torch.cat([self.norm_states(s), z], dim=-1))
        a = mean + std * torch.randn_like(std) if sample else mean
        return a * self.action_std + self.action_mean

    @torch.no_grad()
    def infer_skill(
        self, states: torch.Tensor, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw `states [B, T, sd]` (s_0..T-1), `actions [B, T, ad]` -> posterior mean, std."""
        return self.posterior(self.norm_states(states), self.norm_actions(actions))
