"""Train stage: EM (or naive VI) on the segments, dvclive metrics, best checkpoint, resume.

Runs single-process (`oposm train`) or data-parallel under Hugging Face Accelerate
(`accelerate launch cli.py train`): every process holds the same model (same seed), samples its
own windows, and gradients are averaged across processes before each optimizer step.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from pathlib import Path

import torch

from pipeline.config import Params, TrainParams
from pipeline.devices import resolve_device
from pipeline.errors import UserError
from pipeline.model import SkillModel, SkillModelConfig, save_model
from pipeline.model.checkpoint import CONFIG_FILE, WEIGHTS_FILE
from pipeline.paths import Paths
from pipeline.segments import Segments, load_segments
from pipeline.training.data import WindowSampler
from pipeline.training.loop import Budget, Callbacks, Trainer
from pipeline.training.state import Progress, load_state, save_state
from pipeline.training.updaters import make_updater

log = logging.getLogger(__name__)

# Params that change how long a run goes, not what it computes: a run may be resumed with new ones.
_BUDGET_KEYS = {"max_steps", "max_minutes", "eval_every", "checkpoint_every", "device"}


def model_config(cfg: TrainParams, segments: Segments) -> SkillModelConfig:
    return SkillModelConfig(
        state_dim=segments.info.state_dim,
        action_dim=segments.info.action_dim,
        z_dim=cfg.z_dim,
        hidden=cfg.hidden,
        tawm_shared_std=cfg.tawm_shared_std,
        min_std=cfg.min_std,
    )


def _fingerprint(cfg: TrainParams, segments_dir: Path, world_size: int) -> str:
    """What a resumable state must match: training params (less budget), data, process count."""
    what = {
        "train": cfg.model_dump(exclude=_BUDGET_KEYS),
        "segments": json.loads((segments_dir / "segments.json").read_text()),
        "processes": world_size,
    }
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()


def _accelerator(device: str):
    from accelerate import Accelerator

    return Accelerator(cpu=resolve_device(device, "train.device").type == "cpu")


def _grad_reducer(accelerator):
    if accelerator.num_processes == 1:
        return lambda params: None

    def reduce(params: list[torch.nn.Parameter]) -> None:
        for p in params:
            if p.grad is not None:
                p.grad.copy_(accelerator.reduce(p.grad, reduction="mean"))

    return reduce


def run(params: Params, paths: Paths, progress_bar: bool = True) -> Progress:
    """Train on `data/segments/<name>/`; write `data/models/<name>/` and dvclive metrics."""
    cfg, name = params.train, params.ingest.name
    segments_dir = paths.segments(name)
    segments = load_segments(segments_dir)
    if segments.info.name != name:
        raise UserError(
            f"{segments_dir} holds segments of dataset '{segments.info.name}', but "
            f"ingest.name is '{name}'; re-run `oposm segment`"
        )
    if segments.starts["validation"].size == 0:
        raise UserError(f"{segments_dir} has no validation windows; give segment.split some")

    accelerator = _accelerator(cfg.device)
    rank, world = accelerator.process_index, accelerator.num_processes
    torch.manual_seed(cfg.seed)  # identical initialization in every process
    model = SkillModel(model_config(cfg, segments))
    stats = segments.stats
    model.set_normalization(stats.state_mean, stats.state_std, stats.action_mean, stats.action_std)
    model.to(accelerator.device)
    updater = make_updater(
        cfg.method, model, cfg.lr_e, cfg.lr_m, cfg.grad_clip, _grad_reducer(accelerator)
    )
    train = WindowSampler(segments, "train", accelerator.device, seed=cfg.seed + 1000 * rank)
    val = WindowSampler(segments, "validation", accelerator.device, seed=cfg.seed)
    val_idx = val.fixed_subset(cfg.val_windows, seed=cfg.seed)

    model_dir, resume_dir = paths.model(name), paths.model(name) / "resume"
    fingerprint = _fingerprint(cfg, segments_dir, world)
    progress = load_state(resume_dir, model, updater.optimizers, train.generator, fingerprint)
    resumed = progress is not None
    if resumed:
        log.info("resuming from step %d (%s)", progress.step, resume_dir)
    else:
        progress = Progress()
        torch.manual_seed(cfg.seed + 1000 * rank)  # each process its own noise from here on
        if accelerator.is_main_process:  # a best model of other params must not outlive them
            for stale in (model_dir / WEIGHTS_FILE, model_dir / CONFIG_FILE):
                stale.unlink(missing_ok=True)

    live = _live(paths.live("train"), resumed) if accelerator.is_main_process else None
    extra = {
        "dataset": segments.info.name,
        "info": segments.info.__dict__,
        "window": segments.window,
    }

    def log_metrics(step: int, metrics: dict[str, float]) -> None:
        if live is not None:
            live.step = step
            for key, value in metrics.items():
                live.log_metric(key, value)
            live.make_summary()

    def save_best(p: Progress) -> None:
        if accelerator.is_main_process:
            save_model(model, model_dir, {**extra, "step": p.step, "val_st_nll": p.best_st_nll})

    def save_resume(p: Progress) -> None:
        if accelerator.is_main_process:
            save_state(resume_dir, model, updater.optimizers, train.generator, p, fingerprint)
        accelerator.wait_for_everyone()

    budget = Budget(
        max_steps=cfg.max_steps,
        max_minutes=cfg.max_minutes,
        batch_size=max(1, cfg.batch_size // world),
        eval_every=cfg.eval_every,
        checkpoint_every=cfg.checkpoint_every,
    )
    trainer = Trainer(
        model,
        updater,
        train,
        val,
        val_idx,
        budget,
        Callbacks(log_metrics, save_best, save_resume),
        progress_bar=progress_bar and accelerator.is_main_process,
    )
    start_step, started = progress.step, time.monotonic()
    progress = trainer.fit(progress)
    run_s = max(time.monotonic() - started, 1e-9)
    if world > 1:
        _check_in_sync(accelerator, model)
    if live is not None:
        live.summary |= {
            "steps": progress.step,
            "best_step": progress.best_step,
            "best_val_st_nll": progress.best_st_nll,
            "wall_s": progress.elapsed_s,
            "steps_per_s": (progress.step - start_step) / run_s,
            "windows_per_s": (progress.step - start_step) * cfg.batch_size / run_s,
            "processes": world,
            "device": str(accelerator.device),
        }
        live.end()
    log.info(
        "trained %d steps in %.0f s; best val s_T NLL %.3f at step %d -> %s",
        progress.step,
        progress.elapsed_s,
        progress.best_st_nll,
        progress.best_step,
        model_dir,
    )
    return progress


def _check_in_sync(accelerator, model: SkillModel) -> None:
    """Every process must hold the same parameters (same init, averaged gradients)."""
    flat = torch.cat([p.detach().flatten() for p in model.parameters()])
    gathered = accelerator.gather(flat[None])
    diff = float((gathered - gathered[0]).abs().max())
    if diff != 0.0:
        raise RuntimeError(f"processes diverged: max parameter difference {diff:g}")
    log.info("%d processes in sync (identical parameters)", accelerator.num_processes)


def _live(directory: Path, resumed: bool):
    from dvclive import Live
    from scmrepo.exceptions import SCMError

    try:
        return Live(dir=str(directory), resume=resumed, save_dvc_exp=False, dvcyaml=None)
    except SCMError as exc:  # dvclive asks git for HEAD, which fails in a repo with no commit
        raise UserError(
            f"dvclive cannot read the git repository ({exc}); commit once (`git commit`) first"
        ) from exc
