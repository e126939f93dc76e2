"""The deploy report: what `reports/deploy/report.json` holds, OPOSM vs LLP, the printed summary."""

from __future__ import annotations

from typing import Any


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b else None


def compare_planners(report: dict[str, Any], ours: str, theirs: str) -> dict[str, Any]:
    """The paper's comparison (§4.2, table 4) of two planning agents that ran the same episodes:
    success per task (and the difference), planning time per replan (p50, p95: one environment's
    share of a batched call) and per episode, FLOPs per replan, and `theirs / ours` ratios."""
    a, b = report["by_agent"][ours], report["by_agent"][theirs]
    out: dict[str, Any] = {}
    for task in report["tasks"]:
        out[task] = {
            f"{ours}_success": a[task]["success_rate"],
            f"{theirs}_success": b[task]["success_rate"],
            "difference": a[task]["success_rate"] - b[task]["success_rate"],
        }
    for key in ("p50", "p95", "mean"):
        x = a["planning"]["per_env_latency_s"][key]
        y = b["planning"]["per_env_latency_s"][key]
        out[f"replan_s_{key}"] = {ours: x, theirs: y, f"{theirs}_over_{ours}": _ratio(y, x)}
    per_episode = {
        agent: sum(r[t]["plan_seconds_per_episode"]["mean"] or 0.0 for t in report["tasks"])
        / len(report["tasks"])
        for agent, r in ((ours, a), (theirs, b))
    }
    out["plan_s_per_episode_mean"] = per_episode | {
        f"{theirs}_over_{ours}": _ratio(per_episode[theirs], per_episode[ours])
    }
    fa, fb = a["flops_per_replan"], b["flops_per_replan"]
    out["flops_per_replan"] = {ours: fa, theirs: fb, f"{theirs}_over_{ours}": _ratio(fb, fa)}
    return out


def _times(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.2f}x"


def _task_line(task: str, t: dict[str, Any], radius: float, unit: str | None) -> str:
    """One task's success line; `unit`: the report's `distance_unit` where goals are object
    configurations judged by the environment's own rule (no radius), else None (metres)."""
    steps = t["steps_to_goal"]["p50"]
    reached = "no episode reached the goal"
    if steps is not None:
        reached = f"median {int(steps)} steps to goal"
    within = "".join(
        f"; {_pct(w['success_rate'])} within {limit} steps"
        for limit, w in t.get("within_steps", {}).items()
    )
    return (
        f"    {task:12s} success {t['successes']}/{t['episodes']} = {_pct(t['success_rate'])} "
        f"[95 % CI {_pct(t['success_ci95_low'])} - {_pct(t['success_ci95_high'])}] "
        + (
            f"within {radius:g} m{within}; {_pct(t['success_rate_r045'])} within 0.45 m; "
            if unit is None
            else f"by the environment's success rule{within}; "
        )
        + reached
        + (f"; {t['errors']} failed episodes" if t["errors"] else "")
        + (f"; fell in {t['fallen']}" if t.get("fallen") else "")
    )


def _planning_line(r: dict[str, Any]) -> str | None:
    p = r["planning"]
    if not p["calls"]:
        return None
    per_env = p["per_env_latency_s"]
    flops = r.get("flops_per_replan")
    counted = f"; {flops / 1e6:,.1f} MFLOP per replan" if flops else ""
    return (
        f"    planning     {p['calls']} batched replans ({p['envs_per_call_mean']:.0f} envs "
        f"each on average): per env p50 {per_env['p50'] * 1e3:.2f} ms, p95 "
        f"{per_env['p95'] * 1e3:.2f} ms per replan; {p['plans_per_s']:.0f} plans/s{counted}"
    )


def _gap_line(gaps: dict[str, Any] | None, unit: str) -> str | None:
    """The optimism gap per task: real minus predicted distance to the goal where a plan's
    executed part ends (positive: optimistic), in `unit` (the keys say `_m` whatever it is)."""
    if not gaps:
        return None
    parts = []
    for task, g in gaps.items():
        gap = g["distance_gap_m"]
        if gap["mean"] is not None:
            lo, hi = gap["ci95"]
            parts.append(f"{task} {gap['mean']:+.3f} {unit} [{lo:+.3f}, {hi:+.3f}]")
    if not parts:
        return None
    return "    optimism     real - predicted distance to goal after each plan: " + "; ".join(parts)


def format_summary(report: dict[str, Any]) -> str:
    """Human-readable lines: per agent, success per task with its 95 % interval and planning
    cost; OPOSM vs LLP when both ran; recordings."""
    lines = [
        f"deploy {report['dataset']} ({report['env_id']}): {', '.join(report['agents'])} on "
        f"{report['episodes']} episodes (max {report['max_steps']} steps) in "
        f"{report['wall_s']:.0f} s on {report['device']}"
    ]
    for agent in report["agents"]:
        r = report["by_agent"][agent]
        lines.append(f"  {agent} ({r['wall_s']:.0f} s of episodes)")  # its tasks' times added
        unit = report.get("distance_unit")
        lines += [
            _task_line(task, r[task], report["success_radius"], unit) for task in report["tasks"]
        ]
        if (planning := _planning_line(r)) is not None:
            lines.append(planning)
        if (gap := _gap_line(r.get("optimism_gap"), unit or "m")) is not None:
            lines.append(gap)
    if (c := report.get("oposm_vs_llp")) is not None:
        t = c["replan_s_p50"]
        lines.append(
            f"  oposm vs llp: replan p50 {t['oposm'] * 1e3:.2f} vs {t['llp'] * 1e3:.2f} ms "
            f"(llp/oposm {_times(t['llp_over_oposm'])}); planning per episode "
            f"{_times(c['plan_s_per_episode_mean']['llp_over_oposm'])}"
        )
    lines.append(
        f"  recordings   {report['recordings']} ({report['recorded_episodes']} episodes): "
        f"`oposm view` or `rerun {report['recordings']}/*.rrd`"
    )
    return "\n".join(lines)
