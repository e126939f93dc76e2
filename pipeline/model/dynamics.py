"""The single-step dynamics model p(s_{t+1} | s_t, a_t): the paper's low-level (LLP) baseline.

§4.1 and appendix D compare the temporally abstract world model with "a single-timestep
low-level dynamics model" rolled forward step by step. This is that model: a `GaussianMLP` (the
same 2-layer ReLU trunk and Gaussian heads as the skill model, appendix C) that predicts the
normalized state change `(s_{t+1} - s_t - delta_mean) / delta_std` from normalized `(s_t, a_t)`,
trained by Gaussian maximum likelihood on the train split's transitions. Predicting the change
rather than the next state is the usual parameterization (mbrl-lib, PETS): at dt = 0.01 s the
change is tiny next to the state, so a network predicting s_{t+1} directly would spend its
capacity on the identity.

Its training is `pipeline.training.dynamics`; its checkpoints (safetensors weights + a JSON config,
no pickle) go through `pipeline.model.checkpoint`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from pipeline.model.networks import GaussianMLP
from pipeline.model.skill_model import diag_normal
from pipeline.readback import PositiveFinite, Size


@dataclass(frozen=True)
class DynamicsConfig:
    """Everything needed to rebuild a `DynamicsModel`. No defaults: `dynamics`
    (`pipeline.config.DynamicsParams`) holds them (`pipeline.model.settings.dynamics_config`).

    Attributes:
        state_dim: Size of a state vector.
        action_dim: Size of an action vector.
        hidden: Width of every hidden layer.
        min_std: Floor added to the predicted std (normalized units).
    """

    state_dim: Size
    action_dim: Size
    hidden: Size
    min_std: PositiveFinite


class DynamicsModel(nn.Module):
    """p(s_{t+1} | s_t, a_t) = N(s_t + delta_mean + delta_std * mu, (delta_std * sigma)^2).

    Holds the train-split normalization statistics as buffers, so its public methods take and
    return raw environment units.
    """

    def __init__(self, config: DynamicsConfig):
        super().__init__()
        self.config = config
        sd, ad = config.state_dim, config.action_dim
        self.net = GaussianMLP(sd + ad, config.hidden, sd, min_std=config.min_std)
        for name, dim in (("state", sd), ("action", ad), ("delta", sd)):
            self.register_buffer(f"{name}_mean", torch.zeros(dim))
            self.register_buffer(f"{name}_std", torch.ones(dim))

    def set_normalization(self, stats: dict[str, np.ndarray]) -> None:
        """Copy `{state,action,delta}_{mean,std}` arrays into the buffers."""
        for name, value in stats.items():
            buffer = getattr(self, name)
            buffer.copy_(torch.as_tensor(value, dtype=buffer.dtype))

    def dist(self, s: torch.Tensor, a: torch.Tensor):
        """Distribution of the normalized change, from raw `s [..., sd]`, `a [..., ad]`."""
        x = torch.cat(
            [(s - self.state_mean) / self.state_std, (a - self.action_mean) / self.action_std], -1
        )
        return diag_normal(*self.net(x))

    def nll(self, s: torch.Tensor, a: torch.Tensor, s_next: torch.Tensor) -> torch.Tensor:
        """Negative log-likelihood `[B]` of raw `s_next` (normalized change units, nats)."""
        target = (s_next - s - self.delta_mean) / self.delta_std
        return -self.dist(s, a).log_prob(target)

    @torch.no_grad()
    def predict(self, s: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw `s [..., sd]`, `a [..., ad]` -> mean, std of s_{t+1} in raw units `[..., sd]`."""
        d = self.dist(s, a).base_dist
        return s + self.delta_mean + d.loc * self.delta_std, d.scale * self.delta_std

    @torch.no_grad()
    def rollout(self, s0: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Mean rollout: raw `s0 [B, sd]`, `actions [B, T, ad]` -> states `[B, T + 1, sd]`.

        Each step feeds the previous predicted mean back in (what an LLP planner does with an
        open-loop action sequence), so errors compound over the T steps.
        """
        states = [s0]
        for t in range(actions.shape[1]):
            states.append(self.predict(states[-1], actions[:, t])[0])
        return torch.stack(states, dim=1)
