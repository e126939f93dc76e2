"""An updater's steps replayed as CUDA graphs (`train.cuda_graph`): the same update, launched
by the GPU instead of the host.

At the paper's sizes one eager EM step launches about a thousand small kernels and the GPU is
busy 17 % of the step's wall time on an H100 (results/speed-gpu.md): Python, the dispatcher
and the launches are the bottleneck. Here each half-step (E, M; or VI's one) is captured once as
two graphs on static batch buffers:

- **grads**: loss, backward into the half's parameters, gradient clipping, its metrics and one
  0-d "all finite" flag;
- **apply**: the Adam step (`capturable`, so its step counts live on the device).

A step copies the batch into the buffers, replays grads, reads the flag (the one host read per
half-step, as in eager), and replays apply only if it is true: a non-finite step changes
nothing, exactly as eagerly. The random draws are the CUDA generator's, graph-safe: a replay
draws what the eager step would have drawn from the same generator state (the warm-up before
capture restores the state it consumed).

The first step runs eagerly (it creates Adam's moments, which the apply graph must find); the
capture follows on the second. Single process only: a multi-process gradient all-reduce is not
captured.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from pipeline.errors import UserError
from pipeline.model.skill_model import SkillModel
from pipeline.training.data import WindowBatch
from pipeline.training.updaters import EMUpdater, HalfStep, VIUpdater, backward, no_reduce

WARMUP_STEPS = 2  # eager runs of each grads function on a side stream before its capture


@dataclass
class _Captured:
    grads: torch.cuda.CUDAGraph
    apply: torch.cuda.CUDAGraph
    metrics: dict[str, torch.Tensor]  # static outputs of `grads`, overwritten by each replay
    finite: torch.Tensor
    norm_name: str
    after_step: Callable[[], None] | None  # the half's, run eagerly after `apply`


class CudaGraphUpdater:
    """Runs `inner`'s steps (EM or VI) as CUDA graph replays; the same interface.

    Raises:
        UserError: the model is not on CUDA, or the gradients are reduced across processes.
    """

    def __init__(self, inner: EMUpdater | VIUpdater):
        device = next(inner.model.parameters()).device
        if device.type != "cuda":
            raise UserError("train.cuda_graph needs the model on CUDA (train.device)")
        if inner.reduce_grads is not no_reduce:
            raise UserError(
                "train.cuda_graph runs single-process only; set it false under accelerate launch"
            )
        self.inner = inner
        self.model: SkillModel = inner.model
        self.optimizers = inner.optimizers
        self.device = device
        self._captured: list[_Captured] | None = None
        self._batch: WindowBatch | None = None
        self._steps = 0

    def extra_state(self) -> dict:
        return self.inner.extra_state()

    def step(self, batch: WindowBatch) -> dict[str, torch.Tensor]:
        """One update; metrics as 0-d device tensors, valid until the next step."""
        self._steps += 1
        if self._steps == 1:  # creates the optimizers' state, which the apply graphs update
            return self.inner.step(batch)
        if self._captured is None:
            self._capture(batch)
        assert self._batch is not None and self._captured is not None
        for mine, theirs in zip(_tensors(self._batch), _tensors(batch), strict=True):
            mine.copy_(theirs)
        metrics: dict[str, torch.Tensor] = {}
        for half in self._captured:
            half.grads.replay()
            metrics |= {
                (half.norm_name if k == "grad_norm" else k): v for k, v in half.metrics.items()
            }
            if not bool(half.finite):  # skipped: nothing changed; the loop stops on it
                return metrics
            half.apply.replay()
            if half.after_step is not None:  # in place, outside the graphs, which read it there
                half.after_step()
        return metrics

    def _capture(self, batch: WindowBatch) -> None:
        self._batch = WindowBatch(*(None if t is None else t.clone() for t in _fields(batch)))
        halves = self.inner.halves
        for half in halves:
            _make_capturable(half.optimizer)
        rng = torch.cuda.get_rng_state(self.device)
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):  # lazy initializations (cuBLAS, cuDNN) outside capture
            for _ in range(WARMUP_STEPS):
                for half in halves:
                    self._grads(half)
                    half.optimizer.zero_grad(set_to_none=True)
        torch.cuda.current_stream(self.device).wait_stream(side)
        captured, pool = [], None
        try:
            for half in halves:
                grads = torch.cuda.CUDAGraph()
                with torch.cuda.graph(grads, pool=pool):
                    metrics, finite = self._grads(half)
                pool = grads.pool()
                apply = torch.cuda.CUDAGraph()
                with torch.cuda.graph(apply, pool=pool):
                    half.optimizer.step()
                captured.append(
                    _Captured(grads, apply, metrics, finite, half.norm_name, half.after_step)
                )
        except RuntimeError as e:
            raise UserError(
                f"train.cuda_graph: capturing the training step failed ({e}); "
                "set train.cuda_graph false"
            ) from e
        torch.cuda.set_rng_state(rng, self.device)  # the warm-up's draws are not the run's
        self._captured = captured

    def _grads(self, half: HalfStep) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        assert self._batch is not None
        loss, metrics = half.loss(self.model, self._batch)
        finite = backward(
            loss, metrics, half.params, half.optimizer, no_reduce, self.inner.grad_clip
        )
        return metrics, finite


def _make_capturable(optimizer: torch.optim.Optimizer) -> None:
    """Adam with its step counts on the parameters' device (set after a resume, whose
    `load_state_dict` restores the saved groups' flags)."""
    for group in optimizer.param_groups:
        group["capturable"] = True
        for p in group["params"]:
            state = optimizer.state.get(p)
            if state and "step" in state:
                state["step"] = state["step"].to(p.device, torch.float32)


def _fields(batch: WindowBatch) -> tuple[torch.Tensor | None, ...]:
    """The batch's tensors in `WindowBatch`'s field order (None where it has no windows after)."""
    return (batch.states, batch.actions, batch.after_states, batch.after_actions)


def _tensors(batch: WindowBatch) -> list[torch.Tensor]:
    """The batch's tensors that are there."""
    return [t for t in _fields(batch) if t is not None]
