"""Building blocks of appendix C: a 2-layer ReLU trunk and Gaussian mean / std heads; and a
mixture of Gaussians on the same trunk (`MixtureGaussianMLP`, not the paper's) for a TAWM whose
outcome has several modes.

Under `torch.autocast` (`train.dtype: bfloat16`) the hidden layers multiply in the low precision,
but each head's output layer, the softplus and everything downstream (log-likelihoods, losses) stay
float32: the outputs are what the losses compare with data, and those layers are a few percent of
the products.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


class GaussianHead(nn.Module):
    """Mean and std networks of appendix C.1: two linear layers each, ReLU after the first.

    The mean has no output activation; the std ends in a softplus (plus `min_std`, so a collapsing
    std cannot produce an infinite log-likelihood). `shared_std=True` outputs one scalar std for
    all `out_dim` elements (the paper's maze TAWM, C.3).
    """

    def __init__(
        self,
        in_dim: int,
        hidden: int,
        out_dim: int,
        shared_std: bool = False,
        min_std: float = 1e-4,
    ):
        super().__init__()
        self.mean = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, out_dim))
        std_dim = 1 if shared_std else out_dim
        self.std = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, std_dim))
        self.out_dim = out_dim
        self.min_std = min_std

    def forward(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """`h [..., in_dim]` -> mean, std `[..., out_dim]` (float32 under autocast too)."""
        std = F.softplus(_float32_output(self.std, h)) + self.min_std
        return _float32_output(self.mean, h), std.expand(*h.shape[:-1], self.out_dim)


def _float32_output(net: nn.Sequential, h: torch.Tensor) -> torch.Tensor:
    """`net(h)`, its last (output) layer in float32 when autocast is on."""
    if not torch.is_autocast_enabled(h.device.type):
        return net(h)
    hidden = net[:-1](h)
    with torch.autocast(h.device.type, enabled=False):
        return net[-1](hidden.float())


def trunk(in_dim: int, hidden: int, layer_norm: bool = False) -> nn.Sequential:
    """Two hidden layers: Linear + ReLU each (appendix C), or with `layer_norm` Linear +
    LayerNorm + SiLU each (DreamerV3's and TD-MPC2's trunks): the normalization keeps the
    layer's output on one scale whatever the size of its input."""
    if not layer_norm:
        return nn.Sequential(
            nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU()
        )
    return nn.Sequential(
        nn.Linear(in_dim, hidden), nn.LayerNorm(hidden), nn.SiLU(),
        nn.Linear(hidden, hidden), nn.LayerNorm(hidden), nn.SiLU(),
    )  # fmt: skip


class GaussianMLP(nn.Module):
    """A 2-layer shared network (`trunk`: ReLU, appendix C.2–C.4, or LayerNorm + SiLU)
    followed by a `GaussianHead`."""

    def __init__(
        self,
        in_dim: int,
        hidden: int,
        out_dim: int,
        shared_std: bool = False,
        min_std: float = 1e-4,
        layer_norm: bool = False,
    ):
        super().__init__()
        self.trunk = trunk(in_dim, hidden, layer_norm)
        self.head = GaussianHead(hidden, hidden, out_dim, shared_std, min_std)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """`x [..., in_dim]` -> mean, std `[..., out_dim]`."""
        return self.head(self.trunk(x))


class MixtureGaussianMLP(nn.Module):
    """The `GaussianMLP` trunk followed by K diagonal Gaussian components and their mixture
    weights: a mixture density network (Bishop, 1994). Not the paper's (its TAWM is one Gaussian):
    where one skill's outcome has several modes (a grasp that holds or slips), one Gaussian's mean
    lies between them and predicts neither, while a mixture keeps each.

    The mean network outputs the K means; the std network outputs the K stds (one scalar each
    with `shared_std`) and, beside them, the K mixture logits.
    """

    def __init__(
        self,
        in_dim: int,
        hidden: int,
        out_dim: int,
        components: int,
        shared_std: bool = False,
        min_std: float = 1e-4,
    ):
        super().__init__()
        if components < 2:
            raise ValueError(f"a mixture has at least 2 components, got {components}")
        self.trunk = trunk(in_dim, hidden)
        self.std_dim = 1 if shared_std else out_dim
        self.mean = nn.Sequential(
            nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, components * out_dim)
        )
        self.std = nn.Sequential(
            nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, components * (self.std_dim + 1))
        )
        self.out_dim, self.components, self.min_std = out_dim, components, min_std

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """`x [..., in_dim]` -> means, stds `[..., K, out_dim]` and logits `[..., K]`."""
        h = self.trunk(x)
        k, batch = self.components, h.shape[:-1]
        means = _float32_output(self.mean, h).unflatten(-1, (k, self.out_dim))
        std_out = _float32_output(self.std, h)
        stds = F.softplus(std_out[..., : k * self.std_dim]) + self.min_std
        stds = stds.unflatten(-1, (k, self.std_dim)).expand(*batch, k, self.out_dim)
        return means, stds, std_out[..., k * self.std_dim :]

    def readout(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """`x [..., in_dim]` -> mean, std `[..., out_dim]` of the most probable component: the
        outcome a planner chains (the mixture's mean may be no outcome at all)."""
        means, stds, logits = self(x)
        index = logits.argmax(-1)[..., None, None].expand(*means.shape[:-2], 1, self.out_dim)
        return means.gather(-2, index).squeeze(-2), stds.gather(-2, index).squeeze(-2)
