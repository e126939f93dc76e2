"""The skill prior and the TAWM mean as the planner evaluates them: the same networks as
`SkillModel.prior` and `SkillModel.tawm` (tests/test_planning.py checks equality), computed with
fewer, larger and in-place operations, because the planner's rollout is the hot path.

- the prior's mean and std heads share one matrix product for their hidden layers (`[h, 2h]`);
- the TAWM's std network is skipped (the planner chains means) unless the plan's cost asks for
  the model's uncertainty (`tawm_mean_std`, one Gaussian only); of a mixture TAWM
  (`train.tawm_components`) only its logits are computed, to pick the most probable component;
- the TAWM's input `[s, z]` is never concatenated: its first layer is two accumulated products;
- every ReLU runs in place on the product it follows (no extra allocation);
- optionally in bfloat16 (`dtype`): the weights are cast once, each network's input is cast on the
  way in and its output back to float32 on the way out, so the chain of states between skills
  stays in float32 (CPUs with AVX512-BF16 and GPUs multiply bf16 about twice as fast).

The weights are gathered once per `PlannerNets` (per plan), so a model that trains on keeps working.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from pipeline.model.networks import GaussianMLP, MixtureGaussianMLP
from pipeline.model.skill_model import SkillModel


def _weights(layer: nn.Linear, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """`(W^T [in, out], b [out])` of a linear layer (for `torch.addmm(b, x, W^T)`)."""
    return layer.weight.t().to(dtype), layer.bias.to(dtype)


def _relu_layer(x: torch.Tensor, w: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    return torch.addmm(w[1], x, w[0]).relu_()


class PlannerNets:
    """`prior(s)` and `tawm_mean(s, z)` on normalized `[N, ...]` rows (see the module docstring)."""

    def __init__(self, model: SkillModel, dtype: torch.dtype = torch.float32):
        prior, tawm = model.prior, model.tawm
        self.sd = model.config.state_dim
        self.dtype = dtype
        self.prior_trunk = [_weights(prior.trunk[0], dtype), _weights(prior.trunk[2], dtype)]
        head = prior.head
        self.prior_hidden = (
            torch.cat([head.mean[0].weight, head.std[0].weight]).t().to(dtype),
            torch.cat([head.mean[0].bias, head.std[0].bias]).to(dtype),
        )
        self.prior_mean_out = _weights(head.mean[2], dtype)
        self.prior_std_out = _weights(head.std[2], dtype)
        self.min_std = head.min_std
        first = tawm.trunk[0]
        self.tawm_in_s = first.weight[:, : self.sd].t().to(dtype)
        self.tawm_in_z = first.weight[:, self.sd :].t().to(dtype)
        self.tawm_in_b = first.bias.to(dtype)
        self.tawm_trunk2 = _weights(tawm.trunk[2], dtype)
        self.components = getattr(tawm, "components", 1)
        self.residual = model.config.tawm_residual  # the mean is s_0 + the network's output
        mean_net = tawm.mean if self.components > 1 else tawm.head.mean
        self.tawm_head = [_weights(mean_net[0], dtype), _weights(mean_net[2], dtype)]
        if self.components > 1:  # the logits: the std network's last K outputs
            logits = tawm.std[2]
            self.tawm_logits = [
                _weights(tawm.std[0], dtype),
                (logits.weight[-self.components :].t().to(dtype),
                 logits.bias[-self.components :].to(dtype)),
            ]  # fmt: skip
        if self.components == 1:  # the std network, for `tawm_mean_std`
            std_net = tawm.head.std
            self.tawm_std = [_weights(std_net[0], dtype), _weights(std_net[2], dtype)]
            self.tawm_min_std = tawm.head.min_std
        self.hidden = head.mean[0].out_features
        self._check(prior, tawm)

    def _check(self, prior: GaussianMLP, tawm: GaussianMLP | MixtureGaussianMLP) -> None:
        tawm_mean = tawm.mean if isinstance(tawm, MixtureGaussianMLP) else tawm.head.mean
        for trunk, mean in ((prior.trunk, prior.head.mean), (tawm.trunk, tawm_mean)):
            if not (isinstance(trunk[1], nn.ReLU) and isinstance(mean[1], nn.ReLU)):
                raise ValueError("PlannerNets expects the ReLU networks of appendix C")

    def prior(self, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalized `s [N, sd]` -> prior mean, std `[N, z]` (float32)."""
        h = _relu_layer(_relu_layer(s.to(self.dtype), self.prior_trunk[0]), self.prior_trunk[1])
        both = _relu_layer(h, self.prior_hidden)  # [N, 2h]: mean and std hidden layers
        mean = torch.addmm(self.prior_mean_out[1], both[:, : self.hidden], self.prior_mean_out[0])
        std_in = torch.addmm(self.prior_std_out[1], both[:, self.hidden :], self.prior_std_out[0])
        return mean.float(), F.softplus(std_in.float()) + self.min_std

    def _tawm_trunk(self, s: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        s, z = s.to(self.dtype), z.to(self.dtype)
        h = torch.addmm(torch.addmm(self.tawm_in_b, s, self.tawm_in_s), z, self.tawm_in_z).relu_()
        return _relu_layer(h, self.tawm_trunk2)

    def tawm_mean_std(self, s: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalized `s [N, sd]`, skill `z [N, z]` -> the TAWM's mean of s_T `[N, sd]` and its
        std `[N, sd]` (or `[N, 1]`, a shared std), float32; a one-Gaussian TAWM only."""
        if self.components > 1:
            raise ValueError("the TAWM's std in a plan needs train.tawm_components 1")
        h = self._tawm_trunk(s, z)
        mean = torch.addmm(self.tawm_head[1][1], _relu_layer(h, self.tawm_head[0]),
                           self.tawm_head[1][0]).float()  # fmt: skip
        std_in = torch.addmm(self.tawm_std[1][1], _relu_layer(h, self.tawm_std[0]),
                             self.tawm_std[1][0]).float()  # fmt: skip
        return self._from_start(mean, s), F.softplus(std_in) + self.tawm_min_std

    def tawm_mean(self, s: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Normalized `s [N, sd]`, skill `z [N, z]` -> the TAWM mean of s_T `[N, sd]` (float32)."""
        h = self._tawm_trunk(s, z)
        mean = torch.addmm(self.tawm_head[1][1], _relu_layer(h, self.tawm_head[0]),
                           self.tawm_head[1][0]).float()  # fmt: skip
        if self.components == 1:
            return self._from_start(mean, s)
        logits = torch.addmm(self.tawm_logits[1][1], _relu_layer(h, self.tawm_logits[0]),
                             self.tawm_logits[1][0])  # fmt: skip
        means = mean.unflatten(-1, (self.components, self.sd))
        index = logits.argmax(-1)[:, None, None].expand(-1, 1, self.sd)
        return self._from_start(means.gather(1, index).squeeze(1), s)

    def _from_start(self, mean: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """As `SkillModel._from_start`: the network's mean, or the start plus it (residual)."""
        return mean + s.float() if self.residual else mean
