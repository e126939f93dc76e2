"""The ladder of a manipulation dataset: where OPOSM's object moves fail, rung by rung, each
measured on held-out windows or on OGBench's task episodes (stage `ladder@<dataset>` of
`experiments/manipulation/dvc.yaml`, `results/manipulation/<dataset>-ladder.json`, rendered in the
dataset's section of results/manipulation.md).

(a) Skill fidelity (validate, posterior mode): the posterior skills of recorded held-out windows
    executed from the recorded start in MuJoCo; how far the goal dims end from the recording
    (`replay`), against where the TAWM predicts them (`tawm_vs_recorded`) and against not moving
    at all (`no_model_vs_recorded`). `reproduced`: the share of the recorded move the executed
    skills make, 1 - replay / no model.
(b) The TAWM open loop (validate, prior mode): its chained prediction against the real rollout of
    the same prior skills, beside predicting no motion.
(c) Planning with a perfect model (`oposm_sim`, run `runs/oposm_sim/`): the same CEM over the same
    skills, each candidate executed in the simulator (`pipeline/planning/simulated.py`), with a
    small search (its settings in the report).
(d) The whole agent, OPOSM, with the same small search on the same episodes
    (`runs/oposm_ladder/`), and with the pipeline's own settings (`runs/oposm/`, the table's row).

The verdict (rule 1, `versus`, the same episodes): "planning in the simulator reaches the goal
more often than planning with the TAWM": holds -> the TAWM's predictions stop OPOSM at these
settings; does not hold (both low) -> the skills, the cost or the search do.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pipeline.errors import UserError
from pipeline.reporting.common import percent, points, rate_of, read, stamp_text, versus

OVERALL = "ogbench"
TASKS = [f"ogbench-task{i}" for i in range(1, 6)]
# rung -> (run folder under runs/, agent name in its deploy report)
RUNS = {"sim": ("oposm_sim", "oposm_sim"), "same": ("oposm_ladder", "oposm"),
        "pipeline": ("oposm", "oposm")}  # fmt: skip
PLANNER_KEYS = ("horizon", "candidates", "elites", "iterations")


def _skills(section: Mapping[str, Any]) -> list[tuple[int, Mapping[str, Any]]]:
    return sorted((int(k.split("_")[1]), v) for k, v in section.items() if k.startswith("skills_"))


def fidelity(validate: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Rung (a) per number of skills, from validate's posterior mode."""
    out = []
    for k, v in _skills(validate.get("posterior") or {}):
        if "replay_error_mean" not in v:
            continue
        still = v["no_model_recorded_error_mean"]
        out.append({
            "skills": k,
            "replay": v["replay_error_mean"],
            "tawm_vs_recorded": v["tawm_recorded_error_mean"],
            "no_model_vs_recorded": still,
            "reproduced": 1.0 - v["replay_error_mean"] / still if still > 0 else None,
        })  # fmt: skip
    return out


def open_loop(validate: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Rung (b) per number of skills, from validate's prior mode: means and medians."""
    return [{"skills": k, "tawm": v["tawm_error_mean"], "no_model": v["no_model_error_mean"],
             "tawm_median": v["tawm_error_median"], "no_model_median": v["no_model_error_median"]}
            for k, v in _skills(validate.get("prior") or {})]  # fmt: skip


def _run(root: Path, run: str, agent: str) -> dict[str, Any] | None:
    report = read(root / "runs" / run / "reports" / "deploy" / "report.json")
    if not report or agent not in report.get("by_agent", {}):
        return None
    by = report["by_agent"][agent]
    settings = by.get("settings", {})
    return {
        "run": run,
        "agent": agent,
        "episodes_per_task": report["episodes_per_task"],
        "planner": {k: settings.get(k) for k in PLANNER_KEYS},
        "replan_every": by.get("replan_every"),
        "tasks": {t: rate_of(by[t]) for t in [*TASKS, OVERALL] if t in by},
    }


def ladder_report(name: str, root: Path, stamp: Mapping[str, Any]) -> dict[str, Any]:
    """The ladder of the dataset `name` from its data root (see the module docstring)."""
    validate = read(root / "reports" / "validate" / "report.json")
    if not validate:
        raise UserError(f"{root}/reports/validate/report.json is missing: run validate@{name}")
    runs = {rung: _run(root, *where) for rung, where in RUNS.items()}
    for rung in ("sim", "same"):
        if runs[rung] is None:
            run, agent = RUNS[rung]
            raise UserError(f"{root}/runs/{run}: no {agent} deploy report; run its stage first")
    sim, same = runs["sim"], runs["same"]
    if sim["planner"] != same["planner"] or sim["episodes_per_task"] != same["episodes_per_task"]:
        raise UserError(f"{name}: the oposm_sim and oposm_ladder runs differ in their search or "
                        "episodes; the ladder compares them on the same ones")  # fmt: skip
    word, interval = versus(sim["tasks"][OVERALL], same["tasks"][OVERALL])
    return {
        "dataset": name,
        "stamp": dict(stamp),
        "fidelity": fidelity(validate),
        "open_loop": open_loop(validate),
        "position_unit": validate.get("position_unit"),
        "skill_horizon": validate.get("skill_horizon"),
        "runs": runs,
        "verdict": {
            "claim": f"Planning in the simulator reaches the goal more often than planning with "
            f"the TAWM on {name} (the same skills, search and episodes)",
            "verdict": word,
            "interval": interval,
        },
    }


def _row(label: str, run: Mapping[str, Any] | None) -> str:
    if run is None:
        return f"| {label} | – | " + " | ".join("–" for _ in range(6)) + " |"
    t = run["tasks"]
    cells = [percent(t[k]["rate"], *t[k]["ci95"], digits=0) if k in t else "–" for k in TASKS]
    o = t[OVERALL]
    return (f"| {label} | {run['episodes_per_task']} | " + " | ".join(cells)
            + f" | **{percent(o['rate'], *o['ci95'], digits=0)}** |")  # fmt: skip


def render_ladder(ladder: Mapping[str, Any], words: Mapping[str, str]) -> list[str]:
    """Markdown lines of a ladder, for the dataset's section of the page."""
    unit = ladder.get("position_unit") or "observation units"
    steps = ladder.get("skill_horizon")
    sim = ladder["runs"]["sim"]
    search = ", ".join(f"{k} {sim['planner'][k]}" for k in PLANNER_KEYS)
    lines = [f"### Where object moves fail: the ladder ({stamp_text(ladder['stamp'])})", ""]
    fid = ladder["fidelity"]
    if fid:
        lines.append(
            f"- (a) Skill fidelity: the posterior skills of held-out recorded windows executed "
            f"from the recorded start; goal dims' mean distance ({unit}) from the recording "
            f"after k skills of {steps} steps, executed / TAWM / not moving: "
            + "; ".join(f"{r['skills']}: {r['replay']:.2f} / {r['tawm_vs_recorded']:.2f} / "
                        f"{r['no_model_vs_recorded']:.2f}" for r in fid)
            + ". Share of the recorded move the executed skills make: "
            + ", ".join(f"{100 * r['reproduced']:.0f} %" for r in fid
                        if r["reproduced"] is not None) + "."
        )  # fmt: skip
    ol = ladder["open_loop"]
    if ol:
        lines.append(
            "- (b) The TAWM open loop with prior skills, mean (median) error of the goal dims "
            "against the real rollout, TAWM / no model: "
            + "; ".join(f"{r['skills']}: {r['tawm']:.2f} ({r['tawm_median']:.2f}) / "
                        f"{r['no_model']:.2f} ({r['no_model_median']:.2f})" for r in ol) + "."
        )  # fmt: skip
    v = ladder["verdict"]
    lines += [
        f"- (c) and (d): the same CEM over the same skills ({search}; replanning every "
        f"{sim['replan_every']} steps), each candidate scored in the simulator (`oposm_sim`) "
        "or by the TAWM (`oposm`), on the same episodes; and OPOSM with the pipeline's own "
        "planner (the table's row):",
        "",
        "| rung | episodes per task | " + " | ".join(f"task {i}" for i in range(1, 6))
        + " | overall |",
        "|---" * 8 + "|",
        _row("(c) perfect model (`oposm_sim`)", sim),
        _row("(d) OPOSM, the same search", ladder["runs"]["same"]),
        _row("(d) OPOSM, the pipeline's planner", ladder["runs"]["pipeline"]),
        "",
        f"- {v['claim']}: **{words[v['verdict']]}**; difference {points(v['interval'])} points.",
        "",
    ]  # fmt: skip
    return lines
