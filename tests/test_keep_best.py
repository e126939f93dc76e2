"""The Adam loop of the single-step model, BC and GCBC (`pipeline.training.keep_best`)."""

import pytest
import torch
from torch import nn

from pipeline.errors import UserError
from pipeline.training.keep_best import adam_keep_best


def _fit(val_nll: list[float], keep_last: bool = False, loss: float | None = None):
    """A one-weight model whose validations report `val_nll` in turn; its weight after step k is
    recorded by the evaluation, so the kept weight names the kept step."""
    torch.manual_seed(0)
    module = nn.Linear(1, 1)
    modes, weights = [], []

    def evaluate() -> dict[str, float]:
        modes.append(module.training)
        weights.append(module.weight.item())
        return {"nll": val_nll[len(weights) - 1], "other": 0.0}

    def next_loss() -> torch.Tensor:
        out = module(torch.ones(4, 1)).square().mean()
        return out if loss is None else out * loss

    metrics, step = adam_keep_best(
        module, module.parameters(), next_loss, evaluate, lr=0.1,
        max_steps=5 * len(val_nll), eval_every=5, what="toy", fix="lower toy.lr",
        keep_last=keep_last,
    )  # fmt: skip
    return module, metrics, step, weights, modes


def test_the_best_validation_is_kept_and_evaluated_in_eval_mode():
    module, metrics, step, weights, modes = _fit([3.0, 1.0, 2.0])
    assert step == 10 and metrics == {"nll": 1.0, "other": 0.0}
    assert module.weight.item() == weights[1]
    assert modes == [False] * 3 and module.training  # eval mode inside, train mode after


def test_keep_last_keeps_the_final_parameters():
    module, metrics, step, weights, _ = _fit([3.0, 1.0, 2.0], keep_last=True)
    assert step == 15 and metrics["nll"] == 2.0 and module.weight.item() == weights[2]


def test_a_diverging_loss_names_the_step_and_the_fix():
    with pytest.raises(UserError, match=r"toy training diverged at step 1; lower toy.lr"):
        _fit([1.0], loss=float("nan"))
