"""Dynamics stage: the single-step model p(s_{t+1} | s_t, a_t) on the train split's transitions.

It is the paper's low-level (LLP) baseline: `validate` rolls it forward next to the TAWM, and a
low-level planner can reuse it. Writes `data/models/<name>-dynamics/` and
`data/reports/dynamics.json`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from collections.abc import Iterator
from pathlib import Path

import torch

from pipeline.config import Params
from pipeline.errors import UserError
from pipeline.io import write_json
from pipeline.model.dynamics import DynamicsConfig, FitConfig, fit_dynamics, save_dynamics
from pipeline.paths import Paths
from pipeline.segments import load_segments

log = logging.getLogger(__name__)


def dynamics_dir(paths: Paths, name: str) -> Path:
    """`data/models/<name>-dynamics/`: beside the skill model, outside its (persisted) DVC out."""
    return paths.model(f"{name}-dynamics")


def resolve_device(device: str, key: str) -> torch.device:
    """`auto` -> CUDA when available, else CPU; `cuda` without a GPU is a `UserError`."""
    if device == "cuda" and not torch.cuda.is_available():
        raise UserError(f"{key} is cuda but no CUDA GPU is available; use auto or cpu")
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    return torch.device(device)


@contextlib.contextmanager
def single_thread(device: torch.device) -> Iterator[None]:
    """Run torch on one intra-op thread on CPU for a while (restored afterwards).

    Our CPU work is small MLPs on small batches: with 2 threads on 2 cores shared with other
    jobs, torch's threads wait on each other (measured: 1000 dynamics steps 10.4 s with 2
    threads, 4.7 s with 1, at load 2.9; an unlucky EM run went from ~6 steps/s to 15 s/step).
    """
    previous = torch.get_num_threads()
    if device.type == "cpu":
        torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def run(params: Params, paths: Paths) -> dict[str, float]:
    """Train on `data/segments/<name>/`; write the checkpoint and the metrics; return them."""
    cfg, name = params.dynamics, params.ingest.name
    segments = load_segments(paths.segments(name))
    device = resolve_device(cfg.device, "dynamics.device")
    model_config = DynamicsConfig(
        state_dim=segments.info.state_dim,
        action_dim=segments.info.action_dim,
        hidden=cfg.hidden,
        min_std=cfg.min_std,
    )
    fit = FitConfig(**cfg.model_dump(exclude={"hidden", "min_std", "device"}))
    with single_thread(device):
        model, metrics = fit_dynamics(segments, model_config, fit, device)
    extra = {"dataset": segments.info.name, "info": dataclasses.asdict(segments.info)}
    save_dynamics(model, dynamics_dir(paths, name), extra | {"metrics": metrics})
    write_json(paths.report("dynamics"), metrics | {"device": str(device)})
    log.info(
        "dynamics model: val NLL %.3f, one-step RMSE %.2e after %d steps (%.0f s) -> %s",
        metrics["val_nll"],
        metrics["val_rmse"],
        metrics["steps"],
        metrics["wall_s"],
        dynamics_dir(paths, name),
    )
    return metrics
