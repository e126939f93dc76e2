"""Train stage: EM (or naive VI) on the segments, dvclive metrics, best checkpoint, resume.

Runs single-process (`oposm train`) or data-parallel under Hugging Face Accelerate
(`accelerate launch cli.py train`): every process holds the same model (same seed), samples its
own windows, and gradients are averaged across processes before each optimizer step.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import shutil
from pathlib import Path

import torch

from pipeline import cpu_math
from pipeline.config import Params, TrainParams
from pipeline.cpu_math import numerics_follow_threads
from pipeline.devices import AutoThreads, resolve_device
from pipeline.errors import UserError
from pipeline.io import output_lock
from pipeline.model import SkillModel, SkillModelConfig, save_model
from pipeline.model.checkpoint import WEIGHTS_FILE
from pipeline.model.settings import skill_model_config
from pipeline.paths import Paths
from pipeline.segments import Segments, load_segments
from pipeline.training.cuda_graphs import CudaGraphUpdater
from pipeline.training.data import WindowSampler
from pipeline.training.loop import (
    SELECTION_CRITERIA,
    Budget,
    Callbacks,
    DivergenceCheck,
    Trainer,
)
from pipeline.training.state import Progress, load_state, read_progress, save_state
from pipeline.training.updaters import no_reduce, resolve_dtype, updater_for
from stages.report import write_headline, write_timings

log = logging.getLogger(__name__)

BY_CRITERION = "by"  # models/<name>/by/<criterion>/: the best checkpoint of each criterion

# Params that change how long or where a run goes, not what it computes (compile, cuda_graph: the
# same draws, float rounding aside): a run may be resumed with new ones.
# `select` only picks which kept checkpoint is published.
_BUDGET_KEYS = {
    "max_steps",
    "max_minutes",
    "eval_every",
    "checkpoint_every",
    "device",
    "threads",
    "compile",
    "cuda_graph",
    "select",
    "divergence_margin",
    "divergence_evals",
}


def model_config(cfg: TrainParams, segments: Segments) -> SkillModelConfig:
    bounds = {}
    if cfg.action_likelihood == "censored":  # the data's own bounds, where clipping piles up
        actions = segments.actions
        bounds = {"action_low": actions.min(0).tolist(), "action_high": actions.max(0).tolist()}
    sd = segments.info.state_dim
    ignored = set(cfg.policy_ignore_dims)
    if any(not 0 <= d < sd for d in ignored) or len(ignored) == sd:
        raise UserError(
            f"train.policy_ignore_dims {sorted(ignored)}: the states have {sd} dims (0 to "
            f"{sd - 1}); list some of them, not all (docs/manipulation.md)"
        )
    return skill_model_config(cfg, segments.info.state_dim, segments.info.action_dim, **bounds)


# Keys added since states were first saved, with the value every earlier run had.
_ADDED_KEYS = {"tawm_chain": 1, "tawm_residual": False}


def _unchanged_at_default(cfg: TrainParams) -> set[str]:
    """The added keys at their earlier value (the same computation), left out of the
    fingerprint so that states saved before them still resume."""
    return {key for key, before in _ADDED_KEYS.items() if getattr(cfg, key) == before}


def _fingerprint(cfg: TrainParams, segments_dir: Path, world_size: int) -> str:
    """What a resumable state must match: training params (less budget), data, process count,
    and the CPU arithmetic (a state made in another MKL mode would not end bit-identical)."""
    what = {
        "state_format": 2,  # 2: a best checkpoint per selection criterion (best/<criterion>/)
        "train": cfg.model_dump(exclude=_BUDGET_KEYS | _unchanged_at_default(cfg)),
        "segments": json.loads((segments_dir / "segments.json").read_text()),
        "processes": world_size,
        "cpu_math": cpu_math.mode(),
    }
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()


def _accelerator(device: str):
    from accelerate import Accelerator

    return Accelerator(cpu=resolve_device(device, "train.device").type == "cpu")


def _grad_reducer(accelerator):
    if accelerator.num_processes == 1:
        return no_reduce

    def reduce(params: list[torch.nn.Parameter]) -> None:
        for p in params:
            if p.grad is not None:
                p.grad.copy_(accelerator.reduce(p.grad, reduction="mean"))

    return reduce


def run(params: Params, paths: Paths, progress_bar: bool = True) -> Progress:
    """Train on `data/segments/<name>/`; write `data/models/<name>/` and dvclive metrics.

    The work in progress (resume state, best model so far, dvclive logs) lives in a scratch
    folder keyed by the params and data (`Paths.scratch`); the outputs are written from it when
    the run ends, so a killed run resumes, and an old model stays until a new one replaces it.
    """
    cfg, name = params.train, params.ingest.name
    paths.check(*_outputs(paths, name))  # before the minutes of training, not after
    segments_dir = paths.existing(paths.segments(name))
    segments = load_segments(segments_dir)
    if segments.info.name != name:
        raise UserError(
            f"{segments_dir} holds segments of dataset '{segments.info.name}', but "
            f"ingest.name is '{name}'; re-run `oposm segment`"
        )
    if segments.starts["validation"].size == 0:
        raise UserError(f"{segments_dir} has no validation windows; give segment.split some")

    accelerator = _accelerator(cfg.device)
    dtype = resolve_dtype(cfg.dtype, accelerator.device)  # in the fingerprint and summary as run
    if dtype != cfg.dtype:
        log.info("train.dtype auto: %s on %s", dtype, accelerator.device)
        params = params.model_copy(update={"train": cfg.model_copy(update={"dtype": dtype})})
    with contextlib.ExitStack() as stack:
        if accelerator.is_main_process:  # one writer per model folder
            stack.enter_context(output_lock(paths.model(name)))
        device_type = accelerator.device.type
        threads = AutoThreads(
            cfg.threads if device_type == "cpu" else None,
            fixed_numerics=not numerics_follow_threads(device_type, dtype),
        )
        stack.enter_context(threads)
        return _train(params, paths, segments, segments_dir, accelerator, progress_bar, threads)


def _train(
    params: Params,
    paths: Paths,
    segments: Segments,
    segments_dir: Path,
    accelerator,
    progress_bar: bool,
    threads: AutoThreads,
) -> Progress:
    cfg, name = params.train, params.ingest.name
    rank, world = accelerator.process_index, accelerator.num_processes
    main = accelerator.is_main_process
    torch.manual_seed(cfg.seed)  # identical initialization in every process
    model = SkillModel(model_config(cfg, segments))
    stats = segments.stats
    model.set_normalization(stats.state_mean, stats.state_std, stats.action_mean, stats.action_std)
    model.to(accelerator.device)
    updater = updater_for(cfg, model, _grad_reducer(accelerator))
    if cfg.cuda_graph and accelerator.device.type == "cuda":
        updater = CudaGraphUpdater(updater)
    elif cfg.cuda_graph:
        log.info("train.cuda_graph: no CUDA device, eager steps")
    train = WindowSampler(
        segments, "train", accelerator.device, seed=cfg.seed + 1000 * rank, chain=cfg.tawm_chain
    )
    val = WindowSampler(segments, "validation", accelerator.device, seed=cfg.seed)
    val_idx = val.fixed_subset(cfg.val_windows, seed=cfg.seed)

    fingerprint = _fingerprint(cfg, segments_dir, world)
    scratch = paths.scratch("train", f"{name}-{fingerprint[:16]}")
    resume_dir, best_dir, live_dir = scratch / "resume", scratch / "best", scratch / "live"
    progress = _resume(cfg, resume_dir, model, updater, train.generator, fingerprint)
    resumed = progress is not None
    if resumed:
        log.info("resuming from step %d (%s)", progress.step, resume_dir)
    else:
        log.info("training from step 0 (work in progress: %s)", scratch)
        progress = Progress()
        torch.manual_seed(cfg.seed + 1000 * rank)  # each process its own noise from here on
        if main:  # leftovers of a run killed before its first resume state
            shutil.rmtree(best_dir, ignore_errors=True)
            shutil.rmtree(live_dir, ignore_errors=True)
        accelerator.wait_for_everyone()

    live = _live(live_dir, resumed) if main else None
    extra = {
        "dataset": segments.info.name,
        "info": segments.info.__dict__,
        "window": segments.window,
    }

    def log_metrics(step: int, metrics: dict[str, float]) -> None:
        if live is not None:  # wall-clock ones ("time/...") are not outputs: `write_timings`
            live.step = step
            for key, value in metrics.items():
                if not key.startswith("time/"):
                    live.log_metric(key, value)
            live.make_summary()

    def save_best(criterion: str, p: Progress, metrics: dict[str, float]) -> None:
        if main:
            val = {k.removeprefix("val/"): v for k, v in metrics.items() if k.startswith("val/")}
            meta = {**extra, "step": p.step, "selected_by": criterion, "val": val}
            save_model(model, best_dir / criterion, meta | {"val_st_nll": val["st_nll"]})

    def save_resume(p: Progress) -> None:
        if main:
            save_state(
                resume_dir, model, updater.optimizers, train.generator, p, fingerprint,
                updater.extra_state(),
            )  # fmt: skip
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
        Callbacks(log_metrics, save_best, save_resume, threads.tick),
        progress_bar=progress_bar and main,
        divergence=DivergenceCheck(cfg.select, cfg.divergence_margin, cfg.divergence_evals),
    )
    progress = trainer.fit(progress)
    run_s = max(progress.elapsed_s, 1e-9)  # over resumed runs, like `steps`
    if world > 1:
        _check_in_sync(accelerator, model)
    selected_step, selected_value = progress.best_of(cfg.select)
    if live is not None:
        live.summary |= {
            "steps": progress.step,
            "select": cfg.select,
            "best_step": selected_step,
            **{f"best_val_{c}": progress.best_of(c)[1] for c in SELECTION_CRITERIA},
            **{
                f"best_step_by_{c}": progress.best_of(c)[0]
                for c in SELECTION_CRITERIA
                if c != cfg.select
            },
            "diverged": progress.diverged_step is not None,
            "diverged_step": progress.diverged_step,
            "processes": world,
            "device": str(accelerator.device),
            "dtype": cfg.dtype,
            "cpu_math": cpu_math.mode() if accelerator.device.type == "cpu" else None,
        }
        live.end()
        _publish(paths, name, cfg.select, best_dir, live_dir, live.summary)
        write_timings(paths, "train", {
            "wall_s": progress.elapsed_s,
            "steps_per_s": progress.step / run_s,
            "windows_per_s": progress.step * cfg.batch_size / run_s,
            "torch_threads_at_end": torch.get_num_threads(),
            "thread_switches": threads.switches,
        })  # fmt: skip
    if progress.diverged_step is not None:
        log.warning(
            "this run diverged at step %d (metrics/train.json: diverged); the published model "
            "is its best checkpoint, from step %d. Another train.seed may train stably",
            progress.diverged_step,
            selected_step,
        )
    log.info(
        "trained %d steps in %.0f s; best val %s %.3f at step %d -> %s",
        progress.step,
        progress.elapsed_s,
        cfg.select,
        selected_value,
        selected_step,
        paths.model(name),
    )
    return progress


def _resume(
    cfg: TrainParams,
    resume_dir: Path,
    model: SkillModel,
    updater,
    generator: torch.Generator,
    fingerprint: str,
) -> Progress | None:
    """The saved progress of this exact run, restored into model/optimizers/RNGs; else None.

    A state past `train.max_steps` (the budget was lowered) is not continued: keeping the longer
    model would not be what the params say, so the run starts over.
    """
    saved = read_progress(resume_dir, fingerprint)
    if saved is None:
        return None
    if saved.step > cfg.max_steps:
        log.info(
            "the resume state in %s is at step %d, past train.max_steps = %d: starting over",
            resume_dir,
            saved.step,
            cfg.max_steps,
        )
        return None
    return load_state(
        resume_dir, model, updater.optimizers, generator, fingerprint, updater.extra_state()
    )


def _publish(
    paths: Paths, name: str, select: str, best_dir: Path, live_dir: Path, summary: dict
) -> None:
    """Replace the stage's outputs with the finished run's: model (the checkpoint `select`
    picked, and under `by/<criterion>/` the best of every criterion), dvclive reports,
    headline."""
    if not (best_dir / select / WEIGHTS_FILE).exists():
        raise UserError(f"training ended without a validated model in {best_dir}; raise max_steps")
    with paths.staged(*_outputs(paths, name)) as out:  # all of them, or none
        model = out.folder(paths.model(name))
        shutil.copytree(best_dir / select, model, dirs_exist_ok=True)
        for criterion in SELECTION_CRITERIA:
            shutil.copytree(best_dir / criterion, model / BY_CRITERION / criterion)
        shutil.copytree(live_dir, out.folder(paths.live("train")), dirs_exist_ok=True)
        write_headline(paths, "train", summary, out)


def _outputs(paths: Paths, name: str) -> tuple[list[Path], list[Path]]:
    """The stage's outputs: files (the headline), folders (the model, the dvclive reports)."""
    return [paths.metrics("train")], [paths.model(name), paths.live("train")]


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
