"""One optimization step of EM (E-step then M-step) or of naive VI, on one batch.

Gradients are computed only for the parameters a step updates (`backward(inputs=...)`), then
averaged across processes by `reduce_grads` (Accelerate's all-reduce in multi-process runs, a
no-op otherwise), clipped, and applied.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import nn

from pipeline.model.skill_model import SkillModel
from pipeline.training.data import WindowBatch
from pipeline.training.losses import e_step_loss, m_step_loss, vi_loss

GradReducer = Callable[[list[nn.Parameter]], None]


def no_reduce(params: list[nn.Parameter]) -> None:
    """Single-process training: gradients are already complete."""


def _apply(
    loss: torch.Tensor,
    params: list[nn.Parameter],
    optimizer: torch.optim.Optimizer,
    reduce_grads: GradReducer,
    grad_clip: float | None,
) -> float:
    """Backprop `loss` into `params` only, reduce, clip, step; return the gradient norm.

    A non-finite gradient norm skips the step (the parameters and Adam moments stay as they
    were) and is returned, so the loop stops on it with the model still intact.
    """
    optimizer.zero_grad(set_to_none=True)
    loss.backward(inputs=params)
    reduce_grads(params)
    norm = float(torch.nn.utils.clip_grad_norm_(params, grad_clip if grad_clip else float("inf")))
    if math.isfinite(norm):
        optimizer.step()
    else:
        optimizer.zero_grad(set_to_none=True)
    return norm


class EMUpdater:
    """The paper's incremental EM (§2.1, C.5): per batch one Adam step on phi (eq. 15), then
    one Adam step on theta, psi, omega (eq. 16)."""

    def __init__(
        self,
        model: SkillModel,
        lr_e: float,
        lr_m: float,
        grad_clip: float | None = None,
        reduce_grads: GradReducer = no_reduce,
    ):
        self.model = model
        self.e_params = list(model.posterior.parameters())
        self.m_params = model.generative()
        self.optimizers = {
            "e": torch.optim.Adam(self.e_params, lr=lr_e),
            "m": torch.optim.Adam(self.m_params, lr=lr_m),
        }
        self.grad_clip = grad_clip
        self.reduce_grads = reduce_grads

    def e_step(self, batch: WindowBatch) -> dict[str, float]:
        """One Adam step on the posterior (phi) minimizing eq. 15."""
        loss, metrics = e_step_loss(self.model, batch)
        if not math.isfinite(metrics["e_loss"]):
            return metrics  # diverged: change nothing, the loop stops on the non-finite loss
        metrics["e_grad_norm"] = _apply(
            loss, self.e_params, self.optimizers["e"], self.reduce_grads, self.grad_clip
        )
        return metrics

    def m_step(self, batch: WindowBatch) -> dict[str, float]:
        """One Adam step on policy, TAWM and prior (theta, psi, omega) minimizing eq. 16."""
        loss, metrics = m_step_loss(self.model, batch)
        metrics["m_grad_norm"] = _apply(
            loss, self.m_params, self.optimizers["m"], self.reduce_grads, self.grad_clip
        )
        return metrics

    def step(self, batch: WindowBatch) -> dict[str, float]:
        e_metrics = self.e_step(batch)
        if not all(math.isfinite(v) for v in e_metrics.values()):
            return e_metrics  # diverged: the loop stops; don't push NaNs into theta, psi, omega
        return e_metrics | self.m_step(batch)


class VIUpdater:
    """Naive VI (eq. 1): one Adam step on all parameters jointly, maximizing the ELBO."""

    def __init__(
        self,
        model: SkillModel,
        lr: float,
        grad_clip: float | None = None,
        reduce_grads: GradReducer = no_reduce,
    ):
        self.model = model
        self.params = [p for p in model.parameters() if p.requires_grad]
        self.optimizers = {"vi": torch.optim.Adam(self.params, lr=lr)}
        self.grad_clip = grad_clip
        self.reduce_grads = reduce_grads

    def step(self, batch: WindowBatch) -> dict[str, float]:
        loss, metrics = vi_loss(self.model, batch)
        metrics["grad_norm"] = _apply(
            loss, self.params, self.optimizers["vi"], self.reduce_grads, self.grad_clip
        )
        return metrics


def make_updater(
    method: str,
    model: SkillModel,
    lr_e: float,
    lr_m: float,
    grad_clip: float | None,
    reduce_grads: GradReducer = no_reduce,
) -> EMUpdater | VIUpdater:
    """`em` (the paper's algorithm) or `vi` (the naive ablation; uses `lr_m`)."""
    if method == "em":
        return EMUpdater(model, lr_e, lr_m, grad_clip, reduce_grads)
    return VIUpdater(model, lr_m, grad_clip, reduce_grads)
