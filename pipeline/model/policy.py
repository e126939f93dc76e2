"""Gaussian behaviour-cloning policies: p(a | s) (the LLP baseline's action prior) and the
goal-conditioned p(a | s, g) (GCBC, OGBench's static-policy baseline).

Both are a `GaussianMLP` (appendix C's 2-layer ReLU trunk with Gaussian mean / std heads; the paper
code's LLP prior is the same network) over normalized inputs, predicting normalized actions. The
goal g is a position (the state dims `goal_dims`, x-y in a maze), normalized with the states' own
statistics. With `learned_std=False` the std is fixed at 1 in normalized units, so the negative
log-likelihood is the squared error up to constants (OGBench's GCBC: `const_std=True`).

Training is `pipeline.training.bc`; checkpoints go through `pipeline.model.checkpoint`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from pipeline.model.networks import GaussianMLP
from pipeline.model.skill_model import diag_normal
from pipeline.readback import Count, PositiveFinite, Size


@dataclass(frozen=True)
class PolicyConfig:
    """Everything needed to rebuild a `GaussianPolicy`. No defaults: `bc` and `gcbc`
    (`pipeline.config.PolicyParams`) hold them (`pipeline.model.settings.policy_config`).

    Attributes:
        state_dim: Size of a state vector.
        action_dim: Size of an action vector.
        goal_dims: State dimensions a goal gives (e.g. `[0, 1]`: x, y); empty for p(a | s).
        hidden: Width of every hidden layer.
        min_std: Floor added to the predicted std (normalized units).
        learned_std: Predict the std; False: fixed at 1 (OGBench's GCBC).
    """

    state_dim: Size
    action_dim: Size
    goal_dims: tuple[Count, ...]
    hidden: Size
    min_std: PositiveFinite
    learned_std: bool

    def __post_init__(self) -> None:
        object.__setattr__(self, "goal_dims", tuple(int(d) for d in self.goal_dims))
        if any(not 0 <= d < self.state_dim for d in self.goal_dims):
            raise ValueError(
                f"goal_dims {list(self.goal_dims)} must be state dims (0 to {self.state_dim - 1})"
            )


class GaussianPolicy(nn.Module):
    """p(a | s) or p(a | s, g): a diagonal Gaussian over actions.

    Holds the train-split normalization statistics as buffers, so its public methods take and
    return raw environment units.
    """

    def __init__(self, config: PolicyConfig):
        super().__init__()
        self.config = config
        sd, ad, gd = config.state_dim, config.action_dim, len(config.goal_dims)
        self.net = GaussianMLP(sd + gd, config.hidden, ad, min_std=config.min_std)
        for name, dim in (("state", sd), ("action", ad)):
            self.register_buffer(f"{name}_mean", torch.zeros(dim))
            self.register_buffer(f"{name}_std", torch.ones(dim))

    @property
    def goal_conditioned(self) -> bool:
        return bool(self.config.goal_dims)

    def set_normalization(self, stats: dict[str, np.ndarray]) -> None:
        """Copy `{state,action}_{mean,std}` arrays into the buffers."""
        for name, value in stats.items():
            buffer = getattr(self, name)
            buffer.copy_(torch.as_tensor(value, dtype=buffer.dtype))

    def _inputs(self, s: torch.Tensor, g: torch.Tensor | None) -> torch.Tensor:
        x = (s - self.state_mean) / self.state_std
        if not self.goal_conditioned:
            return x
        if g is None:
            raise ValueError("a goal-conditioned policy needs goals")
        dims = list(self.config.goal_dims)
        return torch.cat([x, (g - self.state_mean[dims]) / self.state_std[dims]], dim=-1)

    def normalized(
        self, s: torch.Tensor, g: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean, std of the normalized action `[..., ad]` from raw `s [..., sd]` (`g [..., G]`)."""
        mean, std = self.net(self._inputs(s, g))
        return mean, std if self.config.learned_std else torch.ones_like(mean)

    def nll(self, s: torch.Tensor, a: torch.Tensor, g: torch.Tensor | None = None) -> torch.Tensor:
        """Negative log-likelihood `[B]` of raw actions `a` (normalized units, nats)."""
        target = (a - self.action_mean) / self.action_std
        return -diag_normal(*self.normalized(s, g)).log_prob(target)

    @torch.no_grad()
    def action_stats(
        self, s: torch.Tensor, g: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw `s [..., sd]` (`g [..., G]`) -> mean, std of the action in raw units `[..., ad]`."""
        mean, std = self.normalized(s, g)
        return self.action_mean + mean * self.action_std, std * self.action_std
