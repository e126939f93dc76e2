"""Validate stage: the world model vs held-out open-loop MuJoCo rollouts and a single-step model.

Reads the segments, the skill model and the single-step model; writes `data/reports/validate.json`
(DVC metrics), `data/reports/validate/*.csv` (DVC plots) and `data/recordings/validate.rrd`
(Rerun, figure 4 of the paper).
"""

from __future__ import annotations

import csv
import logging
import time
from pathlib import Path
from typing import Any

from pipeline.config import Params
from pipeline.devices import resolve_device, torch_threads
from pipeline.envs.disturbance import Pushes
from pipeline.envs.manipspace import ManipSpaceSpec
from pipeline.envs.spec import make_env_spec
from pipeline.evaluation.compat import check_same_environment
from pipeline.evaluation.open_loop import run_open_loop
from pipeline.evaluation.open_loop_metrics import (
    end_position_table,
    error_table,
    open_loop_report,
)
from pipeline.model.checkpoint import load_dynamics, load_model, skill_horizon
from pipeline.paths import Paths
from pipeline.segments import load_segments
from stages.report import report_files, write_report

log = logging.getLogger(__name__)


def recording_path(paths: Paths) -> Path:
    """`data/recordings/validate.rrd`."""
    return paths.root / "recordings" / "validate.rrd"


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    """Rows of equal keys as a CSV file with a header (`path`: the output's staged temporary)."""
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def run(params: Params, paths: Paths) -> dict[str, Any]:
    """Run the validation of `data/models/<name>/` on `data/segments/<name>/`; return the report."""
    started = time.monotonic()
    cfg, name = params.validation, params.ingest.name
    plots = paths.live("validate")
    csvs = {"errors": plots / "error_vs_horizon.csv", "ends": plots / "end_positions.csv"}
    recording = [recording_path(paths)] if cfg.record_starts else []
    outputs = [*csvs.values(), *recording, *report_files(paths, "validate")]
    paths.check(outputs)  # before the rollouts: a path that cannot be written fails now
    segments = load_segments(paths.existing(paths.segments(name)))
    info = segments.info
    spec = make_env_spec(info.env_id, info.env_kwargs)
    device = resolve_device(cfg.device, "validate.device")
    model, meta = load_model(paths.existing(paths.model(name)), device=device)
    dynamics_path = paths.existing(paths.dynamics(name))
    dynamics, dyn_meta = load_dynamics(dynamics_path, device=device)
    check_same_environment(info, meta, f"the skill model in {paths.model(name)}")
    check_same_environment(info, dyn_meta, f"the dynamics model in {dynamics_path}")

    horizon = skill_horizon(meta, paths.existing(paths.model(name)))
    with torch_threads(1 if device.type == "cpu" else None):
        result = run_open_loop(model, dynamics, segments, spec, horizon, cfg, device)
    norm = (model.state_mean.cpu().numpy(), model.state_std.cpu().numpy())
    report = open_loop_report(result, spec, info.state_names, norm)

    with paths.staged(outputs) as out:  # all of them or none (no CSVs beside an old report)
        write_csv(out.file(csvs["errors"]), error_table(report))
        write_csv(out.file(csvs["ends"]), end_position_table(result, list(spec.goal_dims)))
        if cfg.record_starts and isinstance(spec, ManipSpaceSpec):
            from pipeline.viz.manip_validate import write_validate_recording

            write_validate_recording(
                out.file(recording_path(paths)), result, spec, cfg.record_starts
            )
        elif cfg.record_starts:
            from pipeline.viz.validate import write_recording

            write_recording(out.file(recording_path(paths)), result, spec, cfg.record_starts)
        report["disturbance"] = Pushes.of_dataset(info.generator).to_dict()  # as simulated
        report["timing"]["total_s"] = time.monotonic() - started
        write_report(paths, "validate", report, out)
    _log(report)
    return report


def _log(report: dict[str, Any]) -> None:
    unit = {"observation units": "obs"}.get(report.get("position_unit", "m"), "m")
    for mode in ("prior", "posterior"):
        for key, m in report[mode].items():
            walls = m.get("single_step_wall_crossing")
            log.info(
                "%-9s %-8s %4d steps: position error TAWM %.3f %s, single-step %.3f %s, "
                "no model %.3f %s; TAWM within 1/2 sigma %.2f/%.2f%s",
                mode,
                key,
                m["steps"],
                m["tawm_error_mean"],
                unit,
                m["single_step_error_mean"],
                unit,
                m["no_model_error_mean"],
                unit,
                m["tawm_within_1sigma"],
                m["tawm_within_2sigma"],
                "" if walls is None else f"; single-step in walls {100 * walls:.0f}%",
            )
            if "replay_error_mean" in m:
                log.info(
                    "%-9s %-8s %4d steps: skill replay error %.3f %s (TAWM vs recorded %.3f %s, "
                    "no model %.3f %s)",
                    mode,
                    key,
                    m["steps"],
                    m["replay_error_mean"],
                    unit,
                    m["tawm_recorded_error_mean"],
                    unit,
                    m["no_model_recorded_error_mean"],
                    unit,
                )
