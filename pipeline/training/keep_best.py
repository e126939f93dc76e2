"""The Adam loop of the small supervised models (the single-step model, BC and GCBC): one loss a
step, a validation every `eval_every` steps and at the end, the best validation NLL's parameters
kept (or the last ones)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable

import torch
from torch import nn

from pipeline.errors import UserError

log = logging.getLogger(__name__)


def adam_keep_best(
    module: nn.Module,
    params: Iterable[nn.Parameter],
    next_loss: Callable[[], torch.Tensor],
    evaluate: Callable[[], dict[str, float]],
    *,
    lr: float,
    max_steps: int,
    eval_every: int,
    what: str,
    fix: str,
    keep_last: bool = False,
) -> tuple[dict[str, float], int]:
    """Minimize `next_loss()` (a fresh batch's loss) for `max_steps` Adam steps over `params`;
    load the kept parameters into `module` and return their validation metrics and step.

    `evaluate()` runs with `module` in eval mode and returns metrics with an `nll` key: the
    parameters of the lowest `nll` are kept, or with `keep_last` the final ones.

    Raises:
        UserError: the loss became NaN or inf (`"{what} training diverged at step N; {fix}"`).
    """
    optimizer = torch.optim.Adam(params, lr=lr)
    kept: tuple[dict[str, float], int] | None = None
    state = None
    for step in range(1, max_steps + 1):
        loss = next_loss()
        if not torch.isfinite(loss):
            raise UserError(f"{what} training diverged at step {step}; {fix}")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if step % eval_every == 0 or step == max_steps:
            metrics = evaluate_in_eval_mode(module, evaluate)
            log.info("%s step %d: %s", what, step,
                     ", ".join(f"val {k} {v:.4g}" for k, v in metrics.items()))  # fmt: skip
            last = keep_last and step == max_steps
            if kept is None or metrics["nll"] < kept[0]["nll"] or last:
                state = {k: v.detach().clone() for k, v in module.state_dict().items()}
                kept = (metrics, step)
    assert kept is not None and state is not None  # max_steps >= 1
    module.load_state_dict(state)
    return kept


def evaluate_in_eval_mode(
    module: nn.Module, evaluate: Callable[[], dict[str, float]]
) -> dict[str, float]:
    """`evaluate()` with `module` in eval mode, back in train mode after."""
    module.eval()
    try:
        return evaluate()
    finally:
        module.train()
