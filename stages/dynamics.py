"""Dynamics stage: the single-step model p(s_{t+1} | s_t, a_t) on the train split's transitions.

It is the paper's low-level (LLP) baseline: `validate` rolls it forward next to the TAWM, and a
low-level planner can reuse it. Writes `data/models/<name>-dynamics/` and
`data/reports/dynamics.json`.
"""

from __future__ import annotations

import dataclasses
import logging

from pipeline.config import Params
from pipeline.devices import resolve_device, torch_threads
from pipeline.model.checkpoint import save_dynamics
from pipeline.paths import Paths
from pipeline.segments import load_segments
from pipeline.training.dynamics import fit_dynamics
from stages.report import report_files, split_timings, write_report

log = logging.getLogger(__name__)


def run(params: Params, paths: Paths) -> dict[str, float]:
    """Train on `data/segments/<name>/`; write the checkpoint and the metrics; return them."""
    cfg, name = params.dynamics, params.ingest.name
    files, folders = report_files(paths, "dynamics"), [paths.dynamics(name)]
    paths.check(files, folders)
    segments = load_segments(paths.existing(paths.segments(name)))
    device = resolve_device(cfg.device, "dynamics.device")
    with torch_threads(1 if device.type == "cpu" else None):
        model, metrics = fit_dynamics(segments, cfg, device)
    extra = {"dataset": segments.info.name, "info": dataclasses.asdict(segments.info)}
    with paths.staged(files, folders) as out:  # the model and its report together
        kept = split_timings(metrics)[0]  # the checkpoint's bytes: not its wall time
        save_dynamics(model, out.folder(paths.dynamics(name)), extra | {"metrics": kept})
        write_report(paths, "dynamics", metrics | {"device": str(device)}, out)
    log.info(
        "dynamics model: val NLL %.3f, one-step RMSE %.2e after %d steps (%.0f s) -> %s",
        metrics["val_nll"],
        metrics["val_rmse"],
        metrics["steps"],
        metrics["wall_s"],
        paths.dynamics(name),
    )
    return metrics
