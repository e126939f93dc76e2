"""The deploy report: what `reports/deploy.json` holds and the summary printed after a run."""

from __future__ import annotations

from typing import Any


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def format_summary(report: dict[str, Any]) -> str:
    """Human-readable lines: success per task with its 95 % interval, latency, recordings."""
    lines = [
        f"deploy {report['dataset']} ({report['env_id']}, model step {report['model_step']}): "
        f"{report['episodes']} episodes in {report['wall_s']:.0f} s on {report['device']}"
    ]
    for task in report["tasks"]:
        t = report[task]
        steps = t["steps_to_goal"]["p50"]
        reached = "no episode reached the goal"
        if steps is not None:
            reached = f"median {int(steps)} steps to goal"
        lines.append(
            f"  {task:12s} success {t['successes']}/{t['episodes']} = {_pct(t['success_rate'])} "
            f"[95 % CI {_pct(t['success_ci95_low'])} - {_pct(t['success_ci95_high'])}] "
            f"within {report['success_radius']:g} m; {_pct(t['success_rate_r045'])} within 0.45 m; "
            f"{reached}" + (f"; {t['errors']} failed episodes" if t["errors"] else "")
        )
    p = report["planning"]
    lat = p["call_latency_s"]
    if p["calls"]:
        lines.append(
            f"  planning     {p['calls']} batched replans ({p['envs_per_call_mean']:.0f} envs "
            f"each on average): p50 {lat['p50']:.3f} s, p95 {lat['p95']:.3f} s per call; "
            f"{p['plans_per_s']:.0f} plans/s"
        )
    lines.append(
        f"  recordings   {report['recordings']} ({report['recorded_episodes']} episodes): "
        f"`oposm view` or `rerun {report['recordings']}/*.rrd`"
    )
    return "\n".join(lines)
