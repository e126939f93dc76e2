"""Validate stage: the world model vs held-out data, and vs open-loop MuJoCo rollouts when the
dataset's environment is simulated here, beside a single-step model.

Reads the segments, the skill model and the single-step model; writes
`data/reports/validate/report.json` and `metrics/validate.json` (DVC metrics),
`data/reports/validate/*.csv` (DVC plots) and `data/recordings/validate.rrd` (Rerun: figure 4 of
the paper with a simulator, recorded against predicted per state dimension without one). The
data-only section (`recorded`, `pipeline.evaluation.recorded`) is always there; a robot without a
simulator gets it alone.
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
from pipeline.envs.kitchen import KETTLE_POSITION_DIMS, KitchenSpec
from pipeline.envs.manipspace.env import ManipSpaceSpec
from pipeline.envs.spec import EnvSpec, make_env_spec
from pipeline.errors import UserError
from pipeline.evaluation.compat import check_same_environment
from pipeline.evaluation.open_loop import OpenLoopResult, run_open_loop, start_labels
from pipeline.evaluation.open_loop_metrics import (
    EXPECTED_WITHIN,
    end_position_table,
    error_table,
    open_loop_report,
)
from pipeline.evaluation.recorded import (
    RecordedResult,
    horizons,
    per_dim_table,
    position_dims,
    recorded_report,
    run_recorded,
)
from pipeline.evaluation.recorded import error_table as recorded_error_table
from pipeline.evaluation.recorded import headline as recorded_headline
from pipeline.model.checkpoint import load_dynamics, load_model, skill_horizon
from pipeline.paths import Paths
from pipeline.segments import Segments, load_segments
from stages.report import HEADLINES, report_files

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


def simulator_for(segments: Segments) -> EnvSpec | None:
    """The dataset's simulator, or None when validation can use only the recorded data: no
    environment named (a real robot's data), one not simulated here, or no recorded physics
    states to restore (each but the first said in the log)."""
    info = segments.info
    if not info.env_id:
        return None
    try:
        spec = make_env_spec(info.env_id, info.env_kwargs)
    except UserError as exc:
        log.warning("%s: validating against the recorded data only", exc)
        return None
    if segments.physics is None:
        log.warning(
            "dataset '%s' has no MuJoCo states to restore: validating against the recorded data "
            "only",
            info.name,
        )
        return None
    return spec


def run(params: Params, paths: Paths) -> dict[str, Any]:
    """Run the validation of `data/models/<name>/` on `data/segments/<name>/`; return the report.

    With a simulator: the MuJoCo open-loop rollouts and, beside them, the data-only section
    (`recorded`); without one: the data-only section alone.
    """
    started = time.monotonic()
    cfg, name = params.validation, params.ingest.name
    plots = paths.live("validate")
    csvs = {
        "errors": plots / "error_vs_horizon.csv",
        "ends": plots / "end_positions.csv",
        "recorded_errors": plots / "recorded_error_vs_horizon.csv",
        "recorded_dims": plots / "recorded_error_per_dim.csv",
    }
    recording = [recording_path(paths)] if cfg.record_starts else []
    outputs = [*csvs.values(), *recording, *report_files(paths, "validate")]
    paths.check(outputs)  # before the rollouts: a path that cannot be written fails now
    segments = load_segments(paths.existing(paths.segments(name)))
    info = segments.info
    spec = simulator_for(segments)
    device = resolve_device(cfg.device, "validate.device")
    model, meta = load_model(paths.existing(paths.model(name)), device=device)
    dynamics_path = paths.existing(paths.dynamics(name))
    dynamics, dyn_meta = load_dynamics(dynamics_path, device=device)
    check_same_environment(info, meta, f"the skill model in {paths.model(name)}")
    check_same_environment(info, dyn_meta, f"the dynamics model in {dynamics_path}")

    horizon = skill_horizon(meta, paths.existing(paths.model(name)))
    norm = (model.state_mean.cpu().numpy(), model.state_std.cpu().numpy())
    with torch_threads(1 if device.type == "cpu" else None):
        result = None
        if spec is not None:
            result = run_open_loop(model, dynamics, segments, spec, horizon, cfg, device)
        recorded_started = time.monotonic()
        recorded = run_recorded(
            model,
            dynamics,
            segments,
            horizon,
            cfg.starts,
            cfg.skills,
            cfg.particles,
            cfg.seed,
            device,
            starts=None if result is None else result.starts,  # the same held-out windows
        )
        recorded_s = time.monotonic() - recorded_started
    pos = list(spec.goal_dims) if spec is not None else position_dims(info.state_names)
    section = recorded_report(recorded, info.state_names, info.state_units, norm, pos)
    if result is None:
        report: dict[str, Any] = {
            "skill_horizon": horizon,
            "starts": len(recorded.starts),
            "simulated": False,
            "expected_within": {f"{k}sigma": round(p, 4) for k, p in EXPECTED_WITHIN.items()},
        }
    else:
        report = open_loop_report(result, spec, info.state_names, norm)
        report["simulated"] = True
    report["recorded"] = section

    with paths.staged(outputs) as out:  # all of them or none (no CSVs beside an old report)
        write_csv(out.file(csvs["recorded_errors"]), recorded_error_table(section))
        write_csv(out.file(csvs["recorded_dims"]), per_dim_table(section))
        if result is not None:
            write_csv(out.file(csvs["errors"]), error_table(report))
            write_csv(out.file(csvs["ends"]), end_position_table(result, list(spec.goal_dims)))
        if cfg.record_starts:
            _write_recording(
                out.file(recording_path(paths)),
                result,
                recorded,
                spec,
                segments,
                pos,
                cfg.record_starts,
            )
        if result is not None:
            report["disturbance"] = Pushes.of_dataset(info.generator).to_dict()  # as simulated
        # No seconds in the outputs: they must be byte-identical when rerun with the same inputs.
        out.write_json(paths.report("validate"), report)
        out.write_json(paths.metrics("validate"), headline(report))
    _log(report)
    if result is not None:
        log.info(
            "%d simulator steps in %.1f s (%.0f steps/s)",
            result.sim_steps,
            result.sim_s,
            result.sim_steps / max(result.sim_s, 1e-9),
        )
    log.info(
        "recorded data: %d held-out starts in %.2f s; validate took %.1f s",
        len(recorded.starts),
        recorded_s,
        time.monotonic() - started,
    )
    return report


def headline(report: dict[str, Any]) -> dict[str, Any]:
    """`metrics/validate.json`: the simulator's headline (prior skills) when there is one, and
    the data-only section's (`recorded_*` keys) beside it."""
    sim = HEADLINES["validate"](report) if "prior" in report else {}
    return sim | recorded_headline(report["recorded"])


def _write_recording(
    path: Path,
    result: OpenLoopResult | None,
    recorded: RecordedResult,
    spec: EnvSpec | None,
    segments: Segments,
    pos: list[int],
    n: int,
) -> None:
    """Figure 4 over the simulator's rollouts of the first `n` starts, or the recorded-vs-
    predicted view of them without a simulator (and for the kitchen, which has no view of
    Figure 4 yet: its report has the simulator's numbers all the same)."""
    if result is not None and isinstance(spec, ManipSpaceSpec):
        from pipeline.viz.manip_validate import write_validate_recording

        write_validate_recording(path, result, spec, n)
    elif result is not None and not isinstance(spec, KitchenSpec):
        from pipeline.viz.validate import write_recording

        write_recording(path, result, spec, n)
    else:
        from pipeline.viz.recorded import write_recorded_recording

        if isinstance(spec, KitchenSpec):  # its 3-D view: the kettle's position
            pos = list(KETTLE_POSITION_DIMS)
        labels = start_labels(segments, recorded.starts[:n])
        write_recorded_recording(path, recorded, segments.info.state_names, pos, n, labels)


def _log(report: dict[str, Any]) -> None:
    unit = {"observation units": "obs"}.get(report.get("position_unit", "m"), "m")
    for mode in ("prior", "posterior"):
        for key, m in report.get(mode, {}).items():
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
    _log_recorded(report["recorded"])


def _log_recorded(section: dict[str, Any]) -> None:
    pos = section["position_dims"]
    for key in horizons(section):
        m = section[key]
        where = (
            f"position error TAWM {m['tawm_error_mean']:.3f}, single-step "
            f"{m['single_step_error_mean']:.3f}, no model {m['no_model_error_mean']:.3f}; "
            if pos
            else ""
        )
        log.info(
            "recorded  %-8s %4d steps: %serror in train stds TAWM %.3f, single-step %.3f, "
            "no model %.3f; TAWM within 1/2 sigma %.2f/%.2f",
            key,
            m["steps"],
            where,
            m["tawm_norm_error_mean"],
            m["single_step_norm_error_mean"],
            m["no_model_norm_error_mean"],
            m["tawm_within_1sigma"],
            m["tawm_within_2sigma"],
        )
