"""THE REFERENCE for `oposm bench train`: the paper's EM step as its published code runs it, so the
training benchmark times what the pipeline's update replaces, in the same process, at the same
sizes and on the same windows.

The paper's code (`train_skills_EM.py` and `skill_model.py` of the authors' repository; facts in
the project's notes, not its code) differs from the pipeline's update in cost, not in what it
optimizes:

- the posterior q(z | tau): a 2-layer ReLU MLP on each state, then a **4-layer** bidirectional GRU
  over [embedded state, action] (appendix C.1 describes one layer; the pipeline has one); its
  last hidden states of the top layer feed the mean and std heads;
- prior p(z | s_0), policy pi(a | s, z) at every step, TAWM p(s_T | s_0, z): 2-layer ReLU trunks
  with two-layer mean and softplus-std heads (appendix C), every network on the full state;
- E-step: `model.zero_grad(); E_loss.backward(); E_optimizer.step()`, the loss
  (-log pi - log p(z | s_0) + log q(z | tau)) / (T B) with z ~ q reparameterized: the backward
  runs into every parameter, the generative ones included, though only phi moves;
- M-step: the posterior run again, z drawn from it *with* its graph, the loss
  (-log p(s_T | s_0, z) - log pi - log p(z | s_0)) / (T B), backward into every parameter again.

Eager float32 (or under `torch.autocast` in bfloat16, as the pipeline's `train.dtype`), one
process. Not used by the pipeline; benchmarks only.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.distributions import Independent, Normal
from torch.nn import functional as F

from pipeline.training.data import WindowBatch

GRU_LAYERS = 4  # the paper's code's encoder depth


class _Gaussian(nn.Module):
    """A 2-layer ReLU trunk, then mean and softplus-std heads of two layers each."""

    def __init__(self, in_dim: int, hidden: int, out_dim: int):
        super().__init__()
        self.trunk = nn.Sequential(
            nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU()
        )
        self.mean = nn.Sequential(nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, out_dim))
        self.std = nn.Sequential(nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, out_dim))

    def forward(self, x: torch.Tensor) -> Independent:
        h = self.trunk(x)
        std = F.softplus(self.std(h).float()) + 1e-4
        return Independent(Normal(self.mean(h).float(), std, validate_args=False), 1)


class _Encoder(nn.Module):
    """q(z | tau): per-state MLP embedding, a 4-layer bidirectional GRU, Gaussian heads."""

    def __init__(self, state_dim: int, action_dim: int, z_dim: int, hidden: int):
        super().__init__()
        self.embed = nn.Sequential(
            nn.Linear(state_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU()
        )
        self.gru = nn.GRU(
            hidden + action_dim, hidden, GRU_LAYERS, batch_first=True, bidirectional=True
        )
        self.mean = nn.Sequential(
            nn.Linear(2 * hidden, hidden), nn.ReLU(), nn.Linear(hidden, z_dim)
        )
        self.std = nn.Sequential(nn.Linear(2 * hidden, hidden), nn.ReLU(), nn.Linear(hidden, z_dim))

    def forward(self, states: torch.Tensor, actions: torch.Tensor) -> Independent:
        x = torch.cat([self.embed(states), actions], dim=-1)
        _, h_n = self.gru(x)  # [2 layers x directions, B, h]
        last = torch.cat([h_n[-2], h_n[-1]], dim=-1)  # the top layer's two directions
        std = F.softplus(self.std(last).float()) + 1e-4
        return Independent(Normal(self.mean(last).float(), std, validate_args=False), 1)


class ReferenceEM(nn.Module):
    """The paper code's skill model and its EM step (see the module docstring)."""

    def __init__(self, state_dim: int, action_dim: int, z_dim: int, hidden: int, lr: float):
        super().__init__()
        self.encoder = _Encoder(state_dim, action_dim, z_dim, hidden)
        self.prior = _Gaussian(state_dim, hidden, z_dim)
        self.policy = _Gaussian(state_dim + z_dim, hidden, action_dim)
        self.tawm = _Gaussian(state_dim + z_dim, hidden, state_dim)
        generative = [*self.prior.parameters(), *self.policy.parameters(),
                      *self.tawm.parameters()]  # fmt: skip
        self.e_optimizer = torch.optim.Adam(self.encoder.parameters(), lr=lr)
        self.m_optimizer = torch.optim.Adam(generative, lr=lr)

    def _terms(self, batch: WindowBatch):
        s, a = batch.states[:, :-1], batch.actions
        q = self.encoder(s, a)
        z = q.rsample()
        z_t = z[:, None].expand(-1, s.shape[1], -1)
        log_pi = self.policy(torch.cat([s, z_t], dim=-1)).log_prob(a).sum(-1)
        log_prior = self.prior(batch.states[:, 0]).log_prob(z)
        return q, z, log_pi, log_prior

    def e_loss(self, batch: WindowBatch) -> torch.Tensor:
        q, z, log_pi, log_prior = self._terms(batch)
        scale = batch.actions.shape[0] * batch.actions.shape[1]
        return (-log_pi - log_prior + q.log_prob(z)).sum() / scale

    def m_loss(self, batch: WindowBatch) -> torch.Tensor:
        _, z, log_pi, log_prior = self._terms(batch)
        log_tawm = self.tawm(torch.cat([batch.states[:, 0], z], dim=-1)).log_prob(
            batch.states[:, -1]
        )
        scale = batch.actions.shape[0] * batch.actions.shape[1]
        return (-log_tawm - log_pi - log_prior).sum() / scale

    def step(self, batch: WindowBatch, dtype: torch.dtype = torch.float32) -> dict[str, float]:
        """One E-step then one M-step, as the paper's training loop; both losses (host reads,
        as the paper's loop logs them)."""
        device = batch.states.device.type
        low = dtype != torch.float32
        losses = {}
        for name, loss_fn, optimizer in (("e_loss", self.e_loss, self.e_optimizer),
                                         ("m_loss", self.m_loss, self.m_optimizer)):  # fmt: skip
            with torch.autocast(device, dtype=dtype, enabled=low):
                loss = loss_fn(batch)
            self.zero_grad()
            loss.backward()
            optimizer.step()
            losses[name] = loss.item()
        return losses
