"""One optimization step of EM (E-step then M-step) or of naive VI, on one batch.

Gradients are computed only for the parameters a step updates (`backward(inputs=...)`), then
averaged across processes by `reduce_grads` (Accelerate's all-reduce in multi-process runs, a
no-op otherwise), clipped, and applied.

Metrics stay on the device as 0-d tensors (the loop sums them there and reads them once per
validation). The one host read of a half-step is whether its loss, gradient norm and metrics are
finite: a non-finite one skips the optimizer step, so the model stays intact.

With `compile` (`train.compile`) each loss, forward and backward, runs through `torch.compile`
(the posterior's GRU stays eager: dynamo does not trace RNNs); its random draws are eager's
(inductor's `fallback_random`), so a compiled run samples the same skills as an eager one. With
`train.cuda_graph`, `cuda_graphs.CudaGraphUpdater` replays each `HalfStep` as CUDA graphs.

With `dtype` bfloat16 (`train.dtype`) each loss's forward runs under `torch.autocast`: the hidden
layers and the posterior's GRU multiply in bfloat16 (the backward follows), while the weights,
Adam, the heads' output layers and the losses stay float32 (`networks.GaussianHead`).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import nn

from pipeline.model.skill_model import SkillModel
from pipeline.training.data import WindowBatch
from pipeline.training.losses import e_step_loss, m_step_loss, vi_loss

if TYPE_CHECKING:
    from pipeline.config import TrainParams

GradReducer = Callable[[list[nn.Parameter]], None]
Loss = Callable[[SkillModel, WindowBatch], tuple[torch.Tensor, dict[str, torch.Tensor]]]


def native_bfloat16(cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """Whether this CPU multiplies bfloat16 matrices in hardware fast enough to pay: the AMX-BF16
    flag of Linux's /proc/cpuinfo. AVX512-BF16 alone does not (measured on such a CPU without
    AMX, family 6 model 207: the ant's EM step 2.1x slower in bfloat16 than in float32);
    False where the file does not exist."""
    try:
        flags = cpuinfo.read_text(errors="replace")
    except OSError:
        return False
    return " amx_bf16" in flags


def resolve_dtype(setting: str, device: torch.device, native: bool | None = None) -> str:
    """`train.dtype`: float32 or bfloat16 as is; "auto": bfloat16 on a CPU that multiplies it in
    hardware (`native`, default `native_bfloat16()`), else float32 (on other CPUs bfloat16 is
    emulated or converted and slower; on GPUs not yet measured)."""
    if setting != "auto":
        return setting
    if native is None:
        native = device.type == "cpu" and native_bfloat16()
    return "bfloat16" if device.type == "cpu" and native else "float32"


def in_precision(loss: Loss, dtype: str) -> Loss:
    """`loss` itself (`float32`), or its forward under `torch.autocast` in `dtype`."""
    if dtype == "float32":
        return loss
    low = getattr(torch, dtype)

    def autocast_loss(model: SkillModel, batch: WindowBatch):
        device = batch.states.device.type
        # The cache of cast weights saves about 5 % of a CPU step (the GRU reuses its weights
        # every time step); off on CUDA, where the step may be captured in a CUDA graph.
        with torch.autocast(device, dtype=low, cache_enabled=device == "cpu"):
            return loss(model, batch)

    return autocast_loss


def prepared(loss: Loss, compile: bool, dtype: str) -> Loss:
    """`loss` in `dtype` (`in_precision`), compiled if asked (`maybe_compiled`)."""
    return maybe_compiled(in_precision(loss, dtype), compile)


def maybe_compiled(loss: Loss, compile: bool) -> Loss:
    """`loss` itself, or compiled for a fixed batch shape with eager's random numbers."""
    if not compile:
        return loss
    import torch._inductor.config as inductor

    inductor.fallback_random = True
    return torch.compile(loss, dynamic=False)


def no_reduce(params: list[nn.Parameter]) -> None:
    """Single-process training: gradients are already complete."""


def backward(
    loss: torch.Tensor,
    metrics: dict[str, torch.Tensor],
    params: list[nn.Parameter],
    optimizer: torch.optim.Optimizer,
    reduce_grads: GradReducer,
    grad_clip: float | None,
) -> torch.Tensor:
    """Backprop `loss` into `params` only, reduce, clip; add the gradient norm to `metrics`
    under "grad_norm"; return whether the loss, metrics and norm are all finite, as a 0-d
    bool tensor on the device (no host read)."""
    optimizer.zero_grad(set_to_none=True)
    loss.backward(inputs=params)
    reduce_grads(params)
    norm = torch.nn.utils.clip_grad_norm_(params, grad_clip if grad_clip else float("inf"))
    metrics["grad_norm"] = norm.detach()
    return torch.stack([v.reshape(()) for v in metrics.values()]).isfinite().all()


@dataclass
class HalfStep:
    """One optimizer's part of an update: its loss, the parameters it moves, the optimizer, the
    metric name its gradient norm is reported under, and what runs after each optimizer step it
    takes (`after_step`, e.g. `EMAPrior.update`; not part of a captured CUDA graph)."""

    loss: Loss
    params: list[nn.Parameter]
    optimizer: torch.optim.Optimizer
    norm_name: str
    after_step: Callable[[], None] | None = None


def apply_half(
    half: HalfStep,
    model: SkillModel,
    batch: WindowBatch,
    reduce_grads: GradReducer,
    grad_clip: float | None,
) -> tuple[dict[str, torch.Tensor], bool]:
    """`half`'s loss on `batch`, `backward`, then its optimizer step if everything was finite
    (the one host read); metrics (gradient norm under `half.norm_name`) and whether finite.

    A non-finite loss, metric or gradient norm skips the step (the parameters and Adam moments
    stay as they were), so the loop stops on it with the model still intact.
    """
    loss, metrics = half.loss(model, batch)
    finite = bool(backward(loss, metrics, half.params, half.optimizer, reduce_grads, grad_clip))
    if finite:
        half.optimizer.step()
        if half.after_step is not None:
            half.after_step()
    else:
        half.optimizer.zero_grad(set_to_none=True)
    metrics[half.norm_name] = metrics.pop("grad_norm")
    return metrics, finite


def apply_halves(
    halves: list[HalfStep],
    model: SkillModel,
    batch: WindowBatch,
    reduce_grads: GradReducer,
    grad_clip: float | None,
) -> dict[str, torch.Tensor]:
    """The half-steps in order, stopping after a non-finite one (the loop then stops; a later
    half would only push the NaNs on); their metrics as 0-d tensors on the model's device."""
    metrics: dict[str, torch.Tensor] = {}
    for half in halves:
        half_metrics, finite = apply_half(half, model, batch, reduce_grads, grad_clip)
        metrics |= half_metrics
        if not finite:
            break
    return metrics


class EMAPrior(nn.Module):
    """A slowly moving copy of the skill prior for the E-step (`train.e_prior: ema`): after each
    M-step its weights move `rate` of the way to the prior's (Polyak averaging, as target
    networks in RL and DreamerV3's slow critic).

    In eq. 15 the prior is what holds the posterior in place; when it is the current prior, it
    follows the posterior one M-step behind, so the two can drift together without limit. The
    average moves on a time scale of 1 / rate steps, so the posterior is held to where the
    prior has been.
    """

    def __init__(self, prior: nn.Module, rate: float):
        super().__init__()
        self.net = copy.deepcopy(prior).requires_grad_(False)
        self.rate = rate
        self._source = [prior]  # not a submodule: its weights are the model's

    def forward(self, s0_n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.net(s0_n)

    @torch.no_grad()
    def update(self) -> None:
        for mine, theirs in zip(self.net.parameters(), self._source[0].parameters(), strict=True):
            mine.lerp_(theirs, self.rate)


class EMUpdater:
    """The paper's incremental EM (§2.1, C.5): per batch one Adam step on phi (eq. 15, its KL to
    the prior `e_kl`: sampled or closed_form, `losses.e_step_loss`), then one Adam step on
    theta, psi, omega (eq. 16). With `prior_ema` the E-step's prior is an `EMAPrior` of that
    rate (the paper: the current prior, `prior_ema` None). The settings have no defaults: `train`
    (`pipeline.config.TrainParams`) holds them and `updater_for` passes them."""

    def __init__(
        self,
        model: SkillModel,
        lr_e: float,
        lr_m: float,
        *,
        grad_clip: float | None,
        compile: bool,
        dtype: str,
        e_kl: str,
        prior_ema: float | None,
        reduce_grads: GradReducer = no_reduce,
    ):
        self.model = model
        e_params = list(model.posterior.parameters())
        m_params = model.generative()
        self.optimizers = {
            "e": torch.optim.Adam(e_params, lr=lr_e),
            "m": torch.optim.Adam(m_params, lr=lr_m),
        }
        self.prior_ema = None if prior_ema is None else EMAPrior(model.prior, prior_ema)
        # The E-step then the M-step, in the order `step` runs them.
        e_loss = partial(e_step_loss, kl=e_kl, prior=self.prior_ema)
        self.halves = [
            HalfStep(prepared(e_loss, compile, dtype), e_params,
                     self.optimizers["e"], "e_grad_norm"),
            HalfStep(prepared(m_step_loss, compile, dtype), m_params, self.optimizers["m"],
                     "m_grad_norm", self.prior_ema.update if self.prior_ema else None),
        ]  # fmt: skip
        self.grad_clip = grad_clip
        self.reduce_grads = reduce_grads

    def e_step(self, batch: WindowBatch) -> tuple[dict[str, torch.Tensor], bool]:
        """One Adam step on the posterior (phi) minimizing eq. 15; metrics, and whether they
        were finite (else nothing changed)."""
        return apply_half(self.halves[0], self.model, batch, self.reduce_grads, self.grad_clip)

    def m_step(self, batch: WindowBatch) -> tuple[dict[str, torch.Tensor], bool]:
        """One Adam step on policy, TAWM and prior (theta, psi, omega) minimizing eq. 16."""
        return apply_half(self.halves[1], self.model, batch, self.reduce_grads, self.grad_clip)

    def step(self, batch: WindowBatch) -> dict[str, torch.Tensor]:
        """E-step then M-step (not the M-step after a non-finite E-step)."""
        return apply_halves(self.halves, self.model, batch, self.reduce_grads, self.grad_clip)

    def extra_state(self) -> dict[str, nn.Module]:
        """Modules besides the model and optimizers that a resume state must keep."""
        return {} if self.prior_ema is None else {"prior_ema": self.prior_ema}


class VIUpdater:
    """Naive VI (eq. 1): one Adam step on all parameters jointly, maximizing the ELBO. No
    defaults for the settings, as `EMUpdater`."""

    def __init__(
        self,
        model: SkillModel,
        lr: float,
        *,
        grad_clip: float | None,
        compile: bool,
        dtype: str,
        reduce_grads: GradReducer = no_reduce,
    ):
        self.model = model
        params = [p for p in model.parameters() if p.requires_grad]
        self.optimizers = {"vi": torch.optim.Adam(params, lr=lr)}
        self.halves = [  # the one joint step
            HalfStep(prepared(vi_loss, compile, dtype), params, self.optimizers["vi"], "grad_norm")
        ]
        self.grad_clip = grad_clip
        self.reduce_grads = reduce_grads

    def step(self, batch: WindowBatch) -> dict[str, torch.Tensor]:
        """One joint step; metrics as 0-d tensors on the model's device."""
        return apply_halves(self.halves, self.model, batch, self.reduce_grads, self.grad_clip)

    def extra_state(self) -> dict[str, nn.Module]:
        return {}


def make_updater(
    method: str,
    model: SkillModel,
    lr_e: float,
    lr_m: float,
    *,
    grad_clip: float | None,
    compile: bool,
    dtype: str,
    e_kl: str,
    prior_ema: float | None,
    reduce_grads: GradReducer = no_reduce,
) -> EMUpdater | VIUpdater:
    """`em` (the paper's algorithm; its E-step's KL `e_kl`, its prior an EMA of rate
    `prior_ema` or the current one) or `vi` (the naive ablation; uses `lr_m`), multiplying in
    `dtype` (float32, or bfloat16 under autocast)."""
    common = {
        "grad_clip": grad_clip,
        "compile": compile,
        "dtype": dtype,
        "reduce_grads": reduce_grads,
    }
    if method == "em":
        return EMUpdater(model, lr_e, lr_m, e_kl=e_kl, prior_ema=prior_ema, **common)
    return VIUpdater(model, lr_m, **common)


def updater_for(
    cfg: TrainParams, model: SkillModel, reduce_grads: GradReducer = no_reduce
) -> EMUpdater | VIUpdater:
    """`make_updater` with every setting from the train params (what `oposm train` and
    `oposm bench train` run)."""
    device = next(model.parameters()).device
    return make_updater(
        cfg.method, model, cfg.lr_e, cfg.lr_m, grad_clip=cfg.grad_clip, compile=cfg.compile,
        dtype=resolve_dtype(cfg.dtype, device), e_kl=cfg.e_kl,
        prior_ema=cfg.prior_ema if cfg.e_prior == "ema" else None, reduce_grads=reduce_grads,
    )  # fmt: skip
