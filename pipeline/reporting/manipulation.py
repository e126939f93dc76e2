"""results/manipulation.md + .json: OPOSM, LLP, GCBC and OGBench's scripted oracle on OGBench's
manipulation datasets, beside OGBench's published table and the paper's FrankaKitchen rows, on
`pipeline.reporting.common`'s format, verdict rules and stamp, with the published numbers of
`pipeline.evaluation.published` (`OGBENCH_MANIPULATION`, `KITCHEN_TABLE4`).

One data root per dataset (`experiments/manipulation/dvc.yaml`:
`data/experiments/manipulation/<dataset>/`): the data (ingest, segment; made here by OGBench's
play oracles), training, validation and one deploy run per agent under `runs/<agent>/` (the
oracle's by `oposm oracle`, in the deploy report's layout), every agent on the same episodes of
OGBench's five evaluation tasks (each task's own episode limit: 200, 500 or 750 steps).

Two steps, so that a dataset's report outlives its data root (DVC's cache is local): stage
`dataset@<dataset>` writes `results/manipulation/<dataset>.json` (`dataset_report`) from its
data root; stage `report` writes the page, `results/manipulation.md` and `.json` (`page`), from
every dataset's report.

Verdicts, each with its rule of `pipeline.reporting.common`:

- "OPOSM is above every published method" (OGBench's protocol): rule 3, `above_every`, against
  each method's mean over OGBench's 8 seeds. Our data is CPU-sized (fewer and shorter episodes
  than OGBench's), which the verdict does not excuse: it is on the same tasks and success rule.
- "OPOSM reaches goals more often than LLP" (the paper's kitchen claim, table 4, on this
  benchmark) and "... than GCBC": rule 1, `versus`, on the same episodes.
- Where the dataset has the run `oposm_value` (OPOSM planning with a learned value,
  `value.weight`: not the paper's method, row `oposm + value`): it against every published
  method (rule 3) and against OPOSM with the paper's cost (rule 1, the same episodes).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pipeline.errors import UserError
from pipeline.evaluation.published import KITCHEN_TABLE4, OGBENCH_MANIPULATION, OGBENCH_SEEDS
from pipeline.reporting.common import (
    FAILS,
    HOLDS,
    INCONCLUSIVE,
    above_every,
    mean_std,
    percent,
    points,
    rate_of,
    read,
    stamp_text,
    train_speed,
    versus,
    write_report,
)
from pipeline.reporting.common import write_page as write_results_page
from pipeline.reporting.manipulation_ladder import render_ladder

DATASETS = ("cube-single-play", "cube-double-play", "scene-play", "puzzle-3x3-play",
            "puzzle-4x4-play")  # fmt: skip
TASKS = [f"ogbench-task{i}" for i in range(1, 6)]
OVERALL = "ogbench"
# the pipeline's runs, runs/<run>/, in row order, and the rows of runs not named after their agent
AGENTS = ("oposm", "oposm_value", "llp", "gcbc", "oracle")
RUN_LABELS = {"oposm_value": "oposm + value"}  # OPOSM planning with a learned value (not the paper)
ENV_IDS = {"cube-single-play": "cube-single-v0", "cube-double-play": "cube-double-v0",
           "scene-play": "scene-v0", "puzzle-3x3-play": "puzzle-3x3-v0",
           "puzzle-4x4-play": "puzzle-4x4-v0"}  # fmt: skip


# --- reading the runs ---------------------------------------------------------------------------


def deploy_rows(root: Path) -> list[dict[str, Any]]:
    """The pipeline's deploy runs under `root/runs/<agent>/` (AGENTS; a development run beside
    them is not read) on OGBench's tasks: each agent's `rate` per task and pooled, its episode
    limit and mean final distance (in success tolerances)."""
    rows = []
    for run in AGENTS:
        report = read(root / "runs" / run / "reports" / "deploy" / "report.json")
        if not report or OVERALL not in report.get("tasks", []):
            continue
        for agent, by_task in report["by_agent"].items():
            overall = by_task[OVERALL]
            rows.append({
                "agent": RUN_LABELS.get(run, agent if agent == run else f"{agent} (run {run})"),
                "run": run,
                "episodes_per_task": report["episodes_per_task"],
                "max_steps": report.get("max_steps"),
                "final_distance_mean": overall.get("final_distance_mean"),
                "tasks": {t: rate_of(by_task[t]) for t in [*TASKS, OVERALL] if t in by_task},
            })  # fmt: skip
    return rows


def collect(root: Path) -> dict[str, Any]:
    """One dataset's data root: its stage reports and its agents on OGBench's tasks."""
    reports = root / "reports"
    out: dict[str, Any] = {"data_root": root.as_posix()}
    for stage in ("ingest", "segment", "dynamics", "validate", "value"):
        out[stage] = read(reports / stage / "report.json")
    out["train"] = read(reports / "train" / "metrics.json")
    out["agents"] = deploy_rows(root)
    return out


# --- verdicts -----------------------------------------------------------------------------------


def find_agent(data: Mapping[str, Any], name: str) -> dict[str, Any] | None:
    return next((a for a in data["agents"] if a["agent"] == name), None)


def verdicts(name: str, data: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Every claim this dataset's runs can judge: its words, the verdict, the interval."""
    out = []
    oposm = find_agent(data, "oposm")
    if oposm is None:
        return out
    ours = oposm["tasks"][OVERALL]
    table = OGBENCH_MANIPULATION.get(name)
    if table:
        word, method, interval = above_every(ours, table, OGBENCH_SEEDS)
        out.append({"claim": f"OPOSM is above every published method on {name} (OGBench's "
                    "protocol)", "verdict": word, "interval": interval,
                    "detail": f"OPOSM {percent(ours['rate'], *ours['ci95'])} vs {method} "
                    f"{mean_std(*table[method])} (the method deciding it)"})  # fmt: skip
    for other, what in (("llp", "LLP (the paper's kitchen claim, table 4)"), ("gcbc", "GCBC")):
        theirs = find_agent(data, other)
        if theirs is None:
            continue
        b = theirs["tasks"][OVERALL]
        word, interval = versus(ours, b)
        out.append({"claim": f"OPOSM reaches the goal more often than {what} on {name}",
                    "verdict": word, "interval": interval,
                    "detail": f"OPOSM {percent(ours['rate'], *ours['ci95'])} vs "
                    f"{other} {percent(b['rate'], *b['ci95'])}, the same episodes"})  # fmt: skip
    return out + _value_verdicts(name, data, ours)


def _value_verdicts(name: str, data: Mapping[str, Any], paper_cost: Mapping) -> list[dict]:
    """OPOSM with a learned value (run `oposm_value`) against the table and the paper's cost."""
    row = find_agent(data, RUN_LABELS["oposm_value"])
    if row is None:
        return []
    return alternative_verdicts(
        name, row["tasks"][OVERALL], paper_cost, short="OPOSM + value",
        what="OPOSM with a learned value (`value.weight`, not the paper's)",
        baseline="OPOSM with the paper's cost",
    )  # fmt: skip


def alternative_verdicts(
    name: str, ours: Mapping, oposm: Mapping, short: str, what: str, baseline: str
) -> list[dict]:
    """An alternative to OPOSM's own run (`ours`, pooled rates; `short` names it in the
    details, `what` in the claims) against every published method (rule 3) and against OPOSM's
    run `oposm` (`oposm`, described as `baseline`; rule 1, the same episodes)."""
    out = []
    table = OGBENCH_MANIPULATION.get(name)
    if table:
        word, method, interval = above_every(ours, table, OGBENCH_SEEDS)
        out.append({"claim": f"{what} is above every published method on {name} (OGBench's "
                    "protocol)", "verdict": word, "interval": interval,
                    "detail": f"{short} {percent(ours['rate'], *ours['ci95'])} vs {method} "
                    f"{mean_std(*table[method])} (the method deciding it)"})  # fmt: skip
    word, interval = versus(ours, oposm)
    theirs = percent(oposm["rate"], *oposm["ci95"])
    out.append({"claim": f"{what} reaches the goal more often than {baseline} on {name}",
                "verdict": word, "interval": interval,
                "detail": f"{short} {percent(ours['rate'], *ours['ci95'])} vs OPOSM "
                f"{theirs}, the same episodes"})  # fmt: skip
    return out


# --- rendering ----------------------------------------------------------------------------------


def _cell(r: Mapping[str, Any] | None) -> str:
    return "–" if r is None else percent(r["rate"], *r["ci95"], digits=0)


def _agent_rows(agents: list[dict[str, Any]]) -> list[str]:
    lines = ["| agent | episodes per task | " + " | ".join(f"task {i}" for i in range(1, 6))
             + " | overall | mean final distance (tolerances) |", "|---" * 9 + "|"]  # fmt: skip
    for a in agents:
        t = a["tasks"]
        cells = [_cell(t.get(k)) for k in TASKS]
        dist = a["final_distance_mean"]
        lines.append(f"| {a['agent']} | {a['episodes_per_task']} | " + " | ".join(cells)
                     + f" | **{_cell(t[OVERALL])}** | "
                     + ("–" if dist is None else f"{dist:.2f}") + " |")  # fmt: skip
    return lines


def _data_lines(data: Mapping[str, Any]) -> list[str]:
    lines = []
    ingest, train = data.get("ingest"), data.get("train")
    if ingest:
        goals = ingest.get("goals_per_1000_steps")
        lines.append(f"- Data: {ingest['episodes']:.0f} episodes, {ingest['steps']:.0f} steps "
                     "(OGBench's play recipe, made here)"
                     + ("" if goals is None else f"; {goals:.1f} oracle subtasks completed per "
                        "1000 steps") + ".")  # fmt: skip
    if train:
        val = train["val"]
        lines.append(
            f"- Training (EM): {train['steps']} steps ({train_speed(train)} on "
            f"{train.get('device')}); published checkpoint by "
            f"`{train['select']}` at step {train['best_step']}; validation s_T NLL "
            f"{val['st_nll']:.2f} (posterior skill), {val['st_nll_prior']:.2f} (prior skills)"
            + (f"; diverged: {train['diverged']}" if "diverged" in train else "")
            + "."
        )
    validate = data.get("validate")
    prior = (validate or {}).get("prior") or {}
    if prior:
        lines.append("- Open loop with prior skills (validate), mean error of the predicted "
                     "goal dims (observation units) after "
                     + ", ".join(f"{k.split('_')[1]} skills: TAWM {v['tawm_error_mean']:.2f}, "
                                 f"no model {v['no_model_error_mean']:.2f}"
                                 for k, v in prior.items()) + ".")  # fmt: skip
    value = data.get("value")
    if value:
        rho = value["val_steps_to_go_spearman"]
        rank = "undefined" if rho is None else f"{rho:.2f}"
        took = value["val_recorded_steps_to_go_mean"]
        lines.append(
            f"- Learned value (`oposm value`, for the `oposm + value` row): {value['steps']} "
            "steps; on held-out goals up to `value.eval_horizon` steps ahead it predicts the "
            f"steps to go {value['val_steps_to_go_mae']:.1f} steps off on average (the "
            f"recording took {took:.1f}), rank correlation {rank}."
        )
    return lines


def _variant_lines(variant: Mapping[str, Any]) -> list[str]:
    """The dataset section's line on a variant: what changed, its training, its open loop."""
    parts = [f"- Variant `{variant['label']}` ({variant['what']}; `{variant['settings']}`, run "
             f"`runs/{variant['run']}/`)"]  # fmt: skip
    train = variant.get("train")
    if train:
        val = train["val"]
        parts.append(
            f"EM {train['steps']} steps ({train_speed(train)} on {train.get('device')}, "
            f"{train.get('dtype')}); published checkpoint by `{train['select']}` at step "
            f"{train['best_step']}; validation s_T NLL {val['st_nll']:.2f} (posterior skill), "
            f"{val['st_nll_prior']:.2f} (prior skills)"
        )
    if variant.get("open_loop"):
        parts.append(
            "open loop with prior skills, mean error of the goal dims after "
            + ", ".join(
                f"{r['skills']} skills: TAWM {r['tawm']:.2f}, no model {r['no_model']:.2f}"
                for r in variant["open_loop"]
            )  # fmt: skip
        )
    return ["; ".join(parts) + "."]


def _published_line(name: str) -> str:
    table = OGBENCH_MANIPULATION.get(name)
    if not table:
        return "No published number quoted."
    return (f"Published (OGBench's paper, {name}, {OGBENCH_SEEDS} seeds, 1000 play "
            "episodes of 1001 steps): " + ", ".join(f"{m} {mean_std(*v)}" for m, v in
                                                    table.items()) + ".")  # fmt: skip


_WORDS = {HOLDS: "holds", FAILS: "does not hold", INCONCLUSIVE: "inconclusive"}


def render(results: Mapping[str, Any]) -> str:
    made = ("Made by `uv run dvc repro experiments/manipulation/dvc.yaml` (each dataset's "
            "commands in its section)" if results["stamp"].get("dvc") else
            "Made by `oposm report manipulation page` from the datasets' reports")  # fmt: skip
    lines = [
        "# OGBench manipulation: OPOSM beside OGBench's published table",
        "",
        f"{made}; {stamp_text(results['stamp'])}. Every setting: `params-ogbench-<dataset>.yaml` "
        "(an overlay of `params.yaml`); every number: `manipulation.json`.",
        "",
        "## Verdicts",
        "",
    ]
    if not results["datasets"]:
        lines.append("- None yet: no dataset has a report.")
    for checks in results["verdicts"].values():
        lines += [f"- {c['claim']}: **{_WORDS[c['verdict']]}**: {c['detail']}; difference "
                  f"{points(c['interval'])} points." for c in checks]  # fmt: skip
    lines += [
        "",
        "## Protocol",
        "",
        "- Environments: OGBench's `cube-single-v0`, `cube-double-v0` and `scene-v0` (a UR5e arm "
        "with a 2F-85 gripper, 5-dim actions, 0.05 s per step); the state is OGBench's "
        "observation.",
        "- Tasks: each env's five evaluation tasks, from the exact start state OGBench's "
        "evaluation reset leaves (seeded per episode), goal = the task's object configuration, "
        "success = OGBench's rule (every cube within 0.04 m of its goal; the scene's buttons, "
        "drawer and window in their goal states), episodes of the env's 200 / 500 / 750 steps.",
        "- Data: OGBench's `play` recipe (its plan oracles with smoothed noise 0.1, a new "
        "subtask each time one ends), generated here in each dataset's size (its section; "
        "CPU-sized: fewer steps than OGBench's 1000 episodes of 1001 steps).",
        "- Agents: OPOSM (CEM over skills with the goal cost in success tolerances), LLP (the "
        "paper's low-level planner: a BC action prior and a single-step model), GCBC (ours, on "
        "the goal dims), and the reference row `oracle`: OGBench's own plan oracles (those that "
        "made the data, without their noise) in OGBench's env, one subtask at a time toward the "
        "task's goal (`oposm oracle`, `pipeline/envs/manipspace/solver.py`), on the same starts.",
        "- Intervals: 95 % Wilson; verdicts by the rules of `pipeline/reporting/common.py` "
        "(docs/experiments.md).",
        "",
        "The paper's FrankaKitchen rows (table 4; D4RL's human teleoperation data and the "
        "paper's own tasks: a different benchmark, a reference only): "
        + "; ".join(f"{k}: OPOSM {mean_std(*v['oposm'], digits=1)}, LLP "
                    f"{mean_std(*v['llp'], digits=1)}" for k, v in KITCHEN_TABLE4.items())
        + ".",
        "",
    ]  # fmt: skip
    for name, data in results["datasets"].items():
        lines += [f"## {name}", "", *_data_lines(data)]
        for variant in data.get("variants", []):
            lines += _variant_lines(variant)
        lines += [f"- {note}" for note in data.get("notes", [])]
        lines += [""]
        if data["agents"]:
            lines += ["OGBench's five tasks, success % (95 % Wilson interval):", "",
                      *_agent_rows(data["agents"])]  # fmt: skip
        else:
            lines += ["OGBench's five tasks: not deployed yet."]
        lines += ["", _published_line(name), ""]
        if name in results.get("ladders", {}):
            lines += render_ladder(results["ladders"][name], _WORDS)
        lines += [f"This dataset's report: `results/manipulation/{name}.json`, "
                  f"{stamp_text(data['stamp'])}. Its commands:", "", "```bash",
                  *data.get("commands", []), "```", ""]  # fmt: skip
    return "\n".join(lines)


# --- the report ---------------------------------------------------------------------------------


def runs_json(datasets: Mapping[str, Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Every agent's successes per task, flat: dataset, agent, tasks -> episodes and successes."""
    return [
        {"dataset": name, "agent": a["agent"],
         "tasks": {t: {"episodes": r["episodes"], "successes": r["successes"]}
                   for t, r in a["tasks"].items()}}
        for name, data in datasets.items() for a in data["agents"]
    ]  # fmt: skip


def dataset_report(
    name: str, root: Path, notes: list[str], commands: list[str], stamp: Mapping[str, Any]
) -> dict[str, Any]:
    """One dataset's report (stage `dataset@<dataset>`, `results/manipulation/<dataset>.json`):
    what its data root holds (`collect`), its verdicts, notes, commands and where."""
    if name not in DATASETS:
        raise UserError(f"dataset {name!r} is not one of {', '.join(DATASETS)}")
    data = collect(root) | {"notes": list(notes), "commands": list(commands)}
    return {"dataset": name, "env_id": ENV_IDS[name], "stamp": dict(stamp), **data,
            "verdicts": verdicts(name, data)}  # fmt: skip


def page(
    reports: list[Mapping[str, Any]],
    stamp: Mapping[str, Any],
    ladders: list[Mapping[str, Any]] = (),
    variants: list[Mapping[str, Any]] = (),
) -> dict[str, Any]:
    """The page's JSON (stage `report`, `results/manipulation.json`) from the datasets' reports,
    in `DATASETS`' order: the datasets, their verdicts, the flat runs, the published numbers,
    and the datasets' ladders (`manipulation_ladder`) where there are some."""
    datasets = {r["dataset"]: dict(r)
                for r in sorted(reports, key=lambda r: DATASETS.index(r["dataset"]))}  # fmt: skip
    for variant in variants:
        _add_variant(datasets, variant)
    return {
        "ladders": {ladder["dataset"]: dict(ladder) for ladder in ladders},
        "what": "OPOSM, LLP and GCBC on OGBench's manipulation datasets, beside OGBench's "
        "published table",
        "stamp": dict(stamp),
        "datasets": datasets,
        "verdicts": {name: data["verdicts"] for name, data in datasets.items()},
        "runs": runs_json(datasets),
        "published": {
            name: {m: [round(100 * a), round(100 * b)] for m, (a, b) in table.items()}
            for name, table in OGBENCH_MANIPULATION.items()
        },
        "paper_kitchen": {
            k: {a: list(v) for a, v in row.items()} for k, row in KITCHEN_TABLE4.items()
        },  # fmt: skip
    }


def _add_variant(datasets: dict[str, dict[str, Any]], variant: Mapping[str, Any]) -> None:
    """A variant's row after its dataset's OPOSM rows, its verdicts after the dataset's."""
    data = datasets.get(variant["dataset"])
    if data is None:
        raise UserError(
            f"the variant {variant['label']!r} is of {variant['dataset']}, whose report is not "
            "given: add results/manipulation/<dataset>.json to the page's reports"
        )
    rows = data["agents"]
    at = next((i for i, a in enumerate(rows) if not a["run"].startswith("oposm")), len(rows))
    data["agents"] = [*rows[:at], dict(variant["agent"]), *rows[at:]]
    data["verdicts"] = [*data["verdicts"], *variant["verdicts"]]
    data["variants"] = [*data.get("variants", []), dict(variant)]


def write_dataset(path: Path, report: Mapping[str, Any]) -> None:
    """A dataset's report as JSON."""
    write_report(path, report)


def write_page(out: Path, results: Mapping[str, Any]) -> None:
    """`out/manipulation.json` and `out/manipulation.md`."""
    write_results_page(out, "manipulation", results, render(results))
