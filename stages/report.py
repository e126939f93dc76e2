"""Each stage's report: the detailed JSON under `data/reports/<stage>/`, and its headline.

The headline is the handful of numbers a person compares across runs (`dvc exp show`, `dvc
metrics diff`): a small flat-ish JSON in `metrics/<stage>.json`, git-tracked so every
experiment's commit carries it. Everything else stays in the detailed report.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from pipeline.io import Staging
from pipeline.paths import Paths

Report = dict[str, Any]


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
    picked += ["diverged_step", "wall_s"]
    return _pick(r, [*picked, "steps_per_s"]) | {
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
    latency = (a.get("planning") or {}).get("per_env_latency_s") or {}
    return out | {"plan_s_p50": _round(latency.get("p50"), 6), "flops": a.get("flops_per_replan")}


def _deploy(r: Report) -> Report:
    """Per agent: success per task, replan time (one env's share) and FLOPs per replan."""
    tasks = r.get("tasks", [])
    out: Report = {a: _deploy_agent(r["by_agent"][a], tasks) for a in r.get("agents", [])}
    if (c := r.get("oposm_vs_llp")) is not None:
        out["llp_over_oposm_replan_s"] = _round(c["replan_s_p50"]["llp_over_oposm"])
    return out | {"wall_s": _round(r.get("wall_s"))}


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
    staged in `out` (published with the stage's other outputs), or both at once now."""
    if out is None:
        with paths.staged(report_files(paths, stage)) as staging:
            write_report(paths, stage, report, staging)
        return
    out.write_json(paths.report(stage), report)
    out.write_json(paths.metrics(stage), HEADLINES[stage](report))


def write_headline(paths: Paths, stage: str, report: Report, out: Staging | None = None) -> None:
    """Write only the headline of `report` (its details are written elsewhere, e.g. dvclive),
    staged in `out` or now."""
    if out is None:
        with paths.staged([paths.metrics(stage)]) as staging:
            write_headline(paths, stage, report, staging)
        return
    out.write_json(paths.metrics(stage), HEADLINES[stage](report))
