"""The training loop: budget, periodic validation, best checkpoint, resume state, NaN guard.

Parts come in through the constructor (model, updater, samplers, callbacks), so tests can pass
small real ones. The best checkpoint is kept for each model-selection criterion
(`SELECTION_CRITERIA`); the stage publishes the one `train.select` names. Update steps return
dicts of 0-d tensors; only this loop aggregates them (summed on the device in float64, as Python
floats were) and reads them back once per validation.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from pipeline.errors import UserError
from pipeline.model.skill_model import SkillModel
from pipeline.training.cuda_graphs import CudaGraphUpdater
from pipeline.training.data import WindowSampler
from pipeline.training.losses import validation_metrics
from pipeline.training.state import Progress
from pipeline.training.updaters import EMUpdater, VIUpdater

# Validation metrics a best checkpoint can be chosen by (lower is better):
# st_nll: s_T NLL under the posterior skill (the skill that explains the window's actions);
# st_nll_prior: s_T NLL with the skill marginalized over the prior, as a planner draws it.
SELECTION_CRITERIA = ("st_nll", "st_nll_prior")
PRIOR_SAMPLES = 64  # Monte Carlo skills per window for st_nll_prior

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DivergenceCheck:
    """When a run counts as diverged: its validation `criterion` more than `margin` above its
    best for `evals` validations in a row (a collapsed EM run jumps by several nats and does not
    come back; a stable one stays within a few tenths of its best). `margin` None: no check.

    A diverged run is logged as such and recorded (`Progress.diverged_step`); it goes on to its
    budget, and its best checkpoint (from before the divergence) is what gets published. No
    defaults: `train.select`, `train.divergence_margin` and `train.divergence_evals` hold them.
    """

    criterion: str
    margin: float | None
    evals: int

    def update(self, progress: Progress, value: float) -> bool:
        """Count `value` (the newest validation) against the best; True when this validation
        is the one that finds the run diverged."""
        if self.margin is None:
            return False
        _, best = progress.best_of(self.criterion)
        progress.evals_above_best = (
            progress.evals_above_best + 1 if value > best + self.margin else 0
        )
        if progress.diverged_step is None and progress.evals_above_best >= self.evals:
            progress.diverged_step = progress.step
            return True
        return False


@dataclass
class Budget:
    """When to stop, evaluate and save.

    Attributes:
        max_steps: Total update steps (over resumed runs).
        max_minutes: Total wall-clock minutes (over resumed runs); None for no limit.
        batch_size: Windows per update step (per process).
        eval_every: Steps between validations (and best-checkpoint updates).
        checkpoint_every: Steps between resume-state saves.
    """

    max_steps: int
    max_minutes: float | None
    batch_size: int
    eval_every: int
    checkpoint_every: int


@dataclass
class Callbacks:
    """What the loop calls out to (the stage wires files, dvclive and processes in here).

    Attributes:
        log: `(step, metrics)` after each validation.
        save_best: `(criterion, progress, metrics)` when the validation metric `criterion`
            (one of `SELECTION_CRITERIA`) reached a new minimum.
        save_state: `(progress)` to write the resume state.
        each_step: `()` after every update (cheap: e.g. `AutoThreads.tick`).
    """

    log: Callable[[int, dict[str, float]], None]
    save_best: Callable[[str, Progress, dict[str, float]], None]
    save_state: Callable[[Progress], None]
    each_step: Callable[[], None] = lambda: None


@torch.no_grad()
def evaluate(
    model: SkillModel, sampler: WindowSampler, idx: np.ndarray, batch_size: int = 1024
) -> dict[str, float]:
    """Mean validation metrics over the windows at positions `idx` (see `validation_metrics`);
    `st_nll_prior` with the same `PRIOR_SAMPLES` prior draws at every call (seed 0)."""
    model.eval()
    z_dim = model.config.z_dim
    generator = torch.Generator().manual_seed(0)
    prior_eps = torch.randn(PRIOR_SAMPLES, z_dim, generator=generator).to(sampler.device)
    sums: dict[str, float] = defaultdict(float)
    for start in range(0, len(idx), batch_size):
        chunk = torch.as_tensor(idx[start : start + batch_size])
        for name, values in validation_metrics(model, sampler.gather(chunk), prior_eps).items():
            sums[name] += float(values.sum())
    model.train()
    return {f"val/{k}": v / len(idx) for k, v in sums.items()}


class Trainer:
    """Runs updates until the budget is spent, validating and checkpointing on the way."""

    def __init__(
        self,
        model: SkillModel,
        updater: EMUpdater | VIUpdater | CudaGraphUpdater,
        train: WindowSampler,
        val: WindowSampler,
        val_idx: np.ndarray,
        budget: Budget,
        callbacks: Callbacks,
        progress_bar: bool = True,
        divergence: DivergenceCheck | None = None,
    ):
        self.model = model
        self.updater = updater
        self.train = train
        self.val = val
        self.val_idx = val_idx
        self.budget = budget
        self.callbacks = callbacks
        self.progress_bar = progress_bar
        self.divergence = divergence  # None: no check

    def _out_of_time(self, progress: Progress, started: float, resumed_elapsed: float) -> bool:
        progress.elapsed_s = resumed_elapsed + time.monotonic() - started
        limit = self.budget.max_minutes
        return limit is not None and progress.elapsed_s >= 60 * limit

    def _validate(self, progress: Progress, train_sums: dict[str, torch.Tensor], n: int) -> None:
        names = list(train_sums)
        sums = torch.stack([train_sums[k] for k in names]).tolist() if names else []  # one read
        metrics = {f"train/{k}": v / max(n, 1) for k, v in zip(names, sums, strict=True)}
        metrics |= evaluate(self.model, self.val, self.val_idx)
        metrics["time/elapsed_s"] = progress.elapsed_s  # for error-vs-wall-time plots
        self.callbacks.log(progress.step, metrics)
        check = self.divergence
        if check is not None and check.update(progress, metrics[f"val/{check.criterion}"]):
            step, best = progress.best_of(check.criterion)
            log.warning(
                "training diverged: validation %s has been more than %g above its best (%.3f at "
                "step %d) for %d validations, now %.3f at step %d; the best checkpoint (step %d) "
                "will be published. Try another train.seed, or see results/stability-cpu.md",
                check.criterion, check.margin, best, step, check.evals,
                metrics[f"val/{check.criterion}"], progress.step, step,
            )  # fmt: skip
        for criterion in SELECTION_CRITERIA:
            value = metrics[f"val/{criterion}"]
            if value < progress.best_of(criterion)[1]:
                progress.best[criterion] = {"step": progress.step, "value": value}
                self.callbacks.save_best(criterion, progress, metrics)

    def fit(self, progress: Progress) -> Progress:
        """Train from `progress` (fresh or resumed) until the budget is spent.

        Raises:
            UserError: a loss became NaN/inf (the message names the step; the best checkpoint
                and the last resume state on disk are left as they were).
        """
        b = self.budget
        started, resumed_elapsed = time.monotonic(), progress.elapsed_s
        sums: dict[str, torch.Tensor] = {}
        n = 0
        self.model.train()
        with tqdm(
            total=b.max_steps, initial=progress.step, disable=not self.progress_bar, unit="step"
        ) as bar:
            while progress.step < b.max_steps and not self._out_of_time(
                progress, started, resumed_elapsed
            ):
                metrics = self.updater.step(self.train.sample(b.batch_size))
                values = torch.stack([v.detach().reshape(()).double() for v in metrics.values()])
                if not bool(values.isfinite().all()):  # the loop's one host read per step
                    bad = ", ".join(k for k, v in metrics.items() if not torch.isfinite(v))
                    raise UserError(
                        f"training diverged at step {progress.step + 1} ({bad} not finite); "
                        "the last good checkpoint is kept; lower train.lr_e / train.lr_m "
                        "or set train.grad_clip"
                    )
                progress.step += 1
                n += 1
                for k, v in zip(metrics, values, strict=True):
                    sums[k] = sums[k] + v if k in sums else v
                bar.update(1)
                self.callbacks.each_step()
                if progress.step % b.eval_every == 0:
                    self._validate(progress, sums, n)
                    bar.set_postfix(val_st_nll=f"{progress.best_of('st_nll')[1]:.3f}")
                    sums, n = {}, 0
                if progress.step % b.checkpoint_every == 0:
                    self.callbacks.save_state(progress)
        self._out_of_time(progress, started, resumed_elapsed)
        if n:  # validate the tail of a run that stopped between evaluations
            self._validate(progress, sums, n)
        self.callbacks.save_state(progress)
        return progress
