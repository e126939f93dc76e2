"""Each stage's report: the detailed JSON under `data/reports/<stage>/`, and its headline.

The headline is the handful of numbers a person compares across runs (`dvc exp show`, `dvc
metrics diff`): a small flat-ish JSON in `metrics/<stage>.json`, git-tracked so every
experiment's commit carries it. Everything else stays in the detailed report.

Wall-clock measurements (seconds, rates, planning latencies) differ on every run, and DVC hashes
a stage's outputs: the same params and inputs must give the same bytes. So `write_report` moves
them out of both files into `<data>/timings/<stage>.json` (`Paths.timings`), beside the outputs
but not one of them; `oposm bench ...` is where speed is measured for comparison.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from pipeline.io import Staging, write_json
from pipeline.paths import Paths

Report = dict[str, Any]


# Keys whose values are wall-clock measurements, at any depth of a report (and `replan_s_*`).
TIMING_KEYS = frozenset({
    "seconds", "wall_s", "total_s", "steps_per_s", "windows_per_s", "generate_steps_per_s",
    "sim_steps_per_s", "plans_per_s", "plan_seconds", "plan_seconds_per_episode",
    "call_latency_s", "per_env_latency_s", "plan_s_p50", "plan_s_per_episode_mean",
})  # fmt: skip


def _is_timing(key: str) -> bool:
    return key in TIMING_KEYS or key.startswith("replan_s_")


def split_timings(value: Any) -> tuple[Any, Any]:
    """`value` without its wall-clock measurements (`TIMING_KEYS`, at any depth of nested dicts
    and lists), and those measurements alone in the same nesting (None where there are none)."""
    if isinstance(value, list):
        pairs = [split_timings(v) for v in value]
        timings = [t for _, t in pairs]
        return [k for k, _ in pairs], (timings if any(t is not None for t in timings) else None)
    if not isinstance(value, dict):
        return value, None
    kept: dict[str, Any] = {}
    timings: dict[str, Any] = {}
    for key, item in value.items():
        if _is_timing(key):
            timings[key] = item
            continue
        kept[key], inner = split_timings(item)
        if inner is not None:
            timings[key] = inner
    return kept, (timings or None)


def write_timings(paths: Paths, stage: str, timings: Any) -> None:
    """`timings` (what `split_timings` took out) to `<data>/timings/<stage>.json`, atomically;
    never a stage output (its bytes differ on every run)."""
    if timings:
        paths.timings(stage).parent.mkdir(parents=True, exist_ok=True)
        write_json(paths.timings(stage), timings)


def _round(value: Any, digits: int = 4) -> Any:
    return round(value, digits) if isinstance(value, float) else value


def _pick(report: Report, keys: list[str]) -> Report:
    return {k: _round(report[k]) for k in keys if k in report}


def _ingest(r: Report) -> Report:
    return _pick(r, ["episodes", "steps", "goals_per_1000_steps"])


def _segment(r: Report) -> Report:
    return _pick(r, ["train_windows", "validation_windows", "test_windows"])


def _train(r: Report) -> Report:
    val = r.get("val", {})
    picked = ["best_val_st_nll", "best_val_st_nll_prior", "best_step", "steps", "diverged"]
    picked += ["diverged_step"]
    return _pick(r, picked) | {
        f"val_{k}": _round(val[k]) for k in ("st_nll", "st_error", "action_nll") if k in val
    }


def _dynamics(r: Report) -> Report:
    return _pick(r, ["val_nll", "val_rmse"])


def _policy(r: Report) -> Report:
    return _pick(r, ["val_nll", "val_action_rmse"])


def _validate(r: Report) -> Report:
    """Prior skills (what planning uses): errors at one skill and at the longest horizon."""
    out: Report = {}
    horizons = sorted(r.get("prior", {}), key=lambda k: int(k.split("_")[-1]))
    for key in dict.fromkeys([horizons[0], horizons[-1]] if horizons else []):
        h, k = r["prior"][key], key.split("_")[-1]
        out[f"tawm_error_{k}"] = _round(h["tawm_error_mean"])
        out[f"single_step_error_{k}"] = _round(h["single_step_error_mean"])
    if horizons:
        out["tawm_within_1sigma_1"] = _round(r["prior"][horizons[0]]["tawm_within_1sigma"])
    return out


def _deploy_agent(a: Report, tasks: list[str]) -> Report:
    out: Report = {}
    for task in tasks:
        t = a[task]
        out[task] = {
            "success": _round(t["success_rate"]),
            "ci95_low": _round(t["success_ci95_low"]),
            "ci95_high": _round(t["success_ci95_high"]),
            "episodes": t["episodes"],
            "steps_to_goal_p50": _round((t.get("steps_to_goal") or {}).get("p50")),
        } | {
            f"success_within_{k}": _round(w["success_rate"])
            for k, w in t.get("within_steps", {}).items()
        }
    return out | {"flops": a.get("flops_per_replan")}


def _deploy(r: Report) -> Report:
    """Per agent: success per task and FLOPs per replan (its time: `oposm bench plan`)."""
    tasks = r.get("tasks", [])
    return {a: _deploy_agent(r["by_agent"][a], tasks) for a in r.get("agents", [])}


HEADLINES: dict[str, Callable[[Report], Report]] = {
    "ingest": _ingest,
    "segment": _segment,
    "train": _train,
    "dynamics": _dynamics,
    "bc": _policy,
    "gcbc": _policy,
    "validate": _validate,
    "deploy": _deploy,
}


def report_files(paths: Paths, stage: str) -> list[Path]:
    """The files `write_report` writes: `data/reports/<stage>/report.json` and the headline."""
    return [paths.report(stage), paths.metrics(stage)]


def write_report(paths: Paths, stage: str, report: Report, out: Staging | None = None) -> None:
    """Write `report` to `data/reports/<stage>/report.json` and its headline to `metrics/`:
    staged in `out` (published with the stage's other outputs), or both at once now; its
    wall-clock measurements to `<data>/timings/<stage>.json` instead (`split_timings`)."""
    if out is None:
        with paths.staged(report_files(paths, stage)) as staging:
            write_report(paths, stage, report, staging)
        return
    kept, timings = split_timings(report)
    out.write_json(paths.report(stage), kept)
    out.write_json(paths.metrics(stage), HEADLINES[stage](kept))
    write_timings(paths, stage, timings)


def write_headline(paths: Paths, stage: str, report: Report, out: Staging | None = None) -> None:
    """Write only the headline of `report` (its details are written elsewhere, e.g. dvclive),
    staged in `out` or now."""
    if out is None:
        with paths.staged([paths.metrics(stage)]) as staging:
            write_headline(paths, stage, report, staging)
        return
    out.write_json(paths.metrics(stage), HEADLINES[stage](split_timings(report)[0]))
