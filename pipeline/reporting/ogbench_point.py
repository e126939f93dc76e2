"""results/ogbench-point.md + .json: OPOSM under OGBench's protocol on its point mazes, beside
OGBench's published table (issue 18), on `pipeline.reporting.common`'s format, verdict rules and
stamp, with the published numbers of `pipeline.evaluation.published`: OGBench's (`OGBENCH`) and
the methods that came after it (`AFTER_OGBENCH`).

A row is one `oposm deploy` run (its `reports/deploy/report.json`) on OGBench's five evaluation
tasks: its agent (oposm, or the run's only agent, e.g. gcbc) per task and pooled. A row's dataset
is the maze for its navigate dataset (`medium`, `teleport`) or the maze and `-stitch` for its stitch
dataset (`medium-stitch`).

Two ways to make the report (`oposm report ogbench-point` is the command line of both):

- from run folders named one by one (`collect_run`, `write`): the rows a session ran by hand;
- from the DVC pipeline `experiments/ogbench/dvc.yaml` and its vars file
  `experiments/ogbench/params.yaml` (`load_plan`): stage `dataset@<root>` writes one data root's
  rows (`write_dataset_rows`) to `<data>/rows/<root>.json`, stage `report` assembles every root's
  rows that exist (`report_from_rows`), listing the commands dvc.lock recorded.

Verdict per dataset (rule 3 of `pipeline.reporting.common`, `above_every`): our best OPOSM run
against every method of OGBench's row and every later method quoted, the MOVER interval of our
rate minus each method's mean over its 8 seeds; holds when every interval lies above 0.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from pipeline.errors import UserError
from pipeline.evaluation.published import AFTER_OGBENCH, OGBENCH, OGBENCH_METHODS, OGBENCH_SEEDS
from pipeline.io import atomic_path, write_json
from pipeline.reporting.common import (
    above_every,
    above_published,
    lock_commands,
    mean_std,
    percent,
    points,
    rate_of,
    read,
    stamp_text,
)

TASKS = [f"ogbench-task{i}" for i in range(1, 6)]
OVERALL = "ogbench"
POINT_DATASETS = ("medium", "large", "giant", "teleport")
DATASETS = [*POINT_DATASETS, *(f"{d}-stitch" for d in POINT_DATASETS)]
_KEEP = ("episodes", "successes", "success_rate", "success_ci95_low", "success_ci95_high")


def ogbench_name(dataset: str) -> str:
    """Our dataset key -> OGBench's dataset name: medium -> pointmaze-medium-navigate."""
    return f"pointmaze-{dataset}" + ("" if dataset.endswith("-stitch") else "-navigate")


def published(dataset: str) -> dict[str, tuple[float, float]] | None:
    """OGBench's row for a dataset (method -> (mean, std), fractions), None where not quoted."""
    return OGBENCH.get(ogbench_name(dataset))


def published_after(dataset: str) -> dict[str, tuple[float, float]]:
    """The later methods' numbers for a dataset (method -> (mean, std)), {} where none."""
    return AFTER_OGBENCH.get(ogbench_name(dataset), {})


def every_published(dataset: str) -> dict[str, tuple[float, float]] | None:
    """OGBench's row and the later methods' (each over `OGBENCH_SEEDS` seeds, as
    `above_every` takes one count: tests/test_ogbench_point_report.py holds them to it), None
    where neither is quoted."""
    row = {**(published(dataset) or {}), **published_after(dataset)}
    return row or None


def parse_spec(spec: str) -> tuple[str, str, Path]:
    """`DATASET/LABEL=RUN_DIR` -> (dataset, label, run folder)."""
    name, _, run = spec.partition("=")
    dataset, _, label = name.partition("/")
    if not (run and label) or dataset not in DATASETS:
        raise UserError(
            f"--run {spec!r}: expected DATASET/LABEL=RUN_DIR, DATASET one of {DATASETS}"
        )
    return dataset, label, Path(run)


def collect_run(dataset: str, label: str, run: Path) -> dict[str, Any]:
    """One row: the run's numbers per task and overall, for its agent (oposm, or its only one).

    Raises:
        UserError: no report, no oposm results, or not a run of the ogbench tasks.
    """
    path = run / "reports" / "deploy" / "report.json"
    report = read(path)
    if report is None:
        raise UserError(f"{path} does not exist; run the deploy that writes it first")
    agents = list(report.get("by_agent", {}))
    agent = agents[0] if len(agents) == 1 else "oposm"  # a run of one agent: that agent
    try:
        rows = report["by_agent"][agent]
    except KeyError as exc:
        raise UserError(f"{path}: no oposm results (deploy.agents must include oposm)") from exc
    tasks = {t: {k: rows[t][k] for k in _KEEP} for t in [*TASKS, OVERALL] if t in rows}
    if OVERALL not in tasks:
        raise UserError(f"{path}: not a run of the ogbench tasks (deploy.tasks: [ogbench])")
    return {"dataset": dataset, "label": label, "agent": agent, "run": str(run),
            "env_id": report["env_id"], "max_steps": report["max_steps"],
            "success_radius": report["success_radius"], "wall_s": report.get("wall_s"),
            "tasks": tasks}  # fmt: skip


def _cell(row: dict[str, Any]) -> str:
    return percent(row["success_rate"], row["success_ci95_low"], row["success_ci95_high"], 0)


def _published_rows(datasets: list[str]) -> list[str]:
    methods = OGBENCH_METHODS
    lines = ["| dataset | " + " | ".join(methods) + " | best published |",
             "|---|" + "---|" * (len(methods) + 1)]  # fmt: skip
    for dataset in datasets:
        row = published(dataset)
        if row is None:
            lines.append(f"| {dataset} | " + " | ".join("not quoted" for _ in methods) + " | – |")
            continue
        best = max(methods, key=lambda m: row[m][0])
        lines.append(f"| {dataset} | " + " | ".join(mean_std(*row[m]) for m in methods)
                     + f" | {best} {percent(row[best][0], digits=0)} |")  # fmt: skip
    later = sorted({m for d in datasets for m in published_after(d)})
    if later:
        lines += ["", "Methods published after OGBench, their own runs under its protocol "
                  "(mean ± std over 8 seeds; `pipeline/evaluation/paper_after_ogbench.py` names "
                  "each paper and table):", "", "| dataset | " + " | ".join(later) + " |",
                  "|---|" + "---|" * len(later)]  # fmt: skip
        for dataset in datasets:
            row = published_after(dataset)
            lines.append(f"| {dataset} | " + " | ".join(
                mean_std(*row[m]) if m in row else "–" for m in later) + " |")  # fmt: skip
    return lines


def _verdicts(runs: list[dict[str, Any]], datasets: list[str]) -> list[str]:
    lines = [
        'Verdict per dataset, "OPOSM is above every published method" (OGBench\'s and the later '
        "ones; our best run's 95 % interval against each method's mean over its 8 seeds, the "
        "MOVER interval of the "
        "difference in points: holds when it lies above 0 for every method, does not hold when "
        "below 0 for one; `pipeline/reporting/common.py`, rule 3):",
    ]
    for dataset in datasets:
        ours = [r for r in runs if r["dataset"] == dataset and r["agent"] == "oposm"]
        if not ours:
            continue
        top = max(ours, key=lambda r: r["tasks"][OVERALL]["success_rate"])
        overall = top["tasks"][OVERALL]
        row = every_published(dataset)
        if row is None:
            lines.append(f"- {dataset}: {top['label']} {_cell(overall)}; no published number "
                         "is quoted here to compare with.")  # fmt: skip
            continue
        word, method, interval = above_every(rate_of(overall), row, OGBENCH_SEEDS)
        lines.append(f"- {dataset}: **{word}**: {top['label']} {_cell(overall)} vs {method} "
                     f"{mean_std(*row[method])} (the method deciding it), difference "
                     f"{points(interval, 0)} points.")  # fmt: skip
    checks = [r for r in runs if r["agent"] == "gcbc" and published(r["dataset"])]
    if checks:
        lines += ["", "Our GCBC against OGBench's (the same agent, our implementation and sizes; "
                  "the interval of ours minus OGBench's as above):"]  # fmt: skip
    for r in checks:
        mean, std = published(r["dataset"])["GCBC"]
        overall = r["tasks"][OVERALL]
        _, interval = above_published(rate_of(overall), mean, std, OGBENCH_SEEDS)
        lines.append(f"- {r['dataset']}: ours {_cell(overall)}, OGBench's {mean_std(mean, std)}; "
                     f"difference {points(interval, 0)} points.")  # fmt: skip
    return lines


def render(
    runs: list[dict[str, Any]],
    commands: list[str],
    machine: str,
    stamp: dict[str, Any],
    not_run: list[str] = (),
) -> str:
    """The report: every row, OGBench's table, a verdict per dataset, the commands."""
    made = (
        "Made by `uv run dvc repro experiments/ogbench/dvc.yaml` (every row's stage and command "
        "at the end)"
        if stamp.get("dvc")
        else "Made by `oposm report ogbench-point` from the runs' deploy reports (the "
        "commands that produced them at the end)"
    )
    lines = [
        "# OGBench point mazes: OPOSM under OGBench's protocol, beside its published table",
        "",
        "Success (%) on OGBench's five evaluation tasks per maze (its start and goal cells with "
        "its noise, at most 1000 steps, success within 1.0 of the goal), with 95 % Wilson "
        "intervals; one trained model and one deploy seed per dataset. Dataset: the maze alone is "
        "its navigate dataset, `-stitch` its stitch dataset (both made with OGBench's recipe, "
        "smaller than OGBench's files). Published: OGBench's paper, mean ± std over 8 seeds "
        "(navigate: docs/references.md; stitch: OGBench's table as copied by later papers, whose "
        "navigate rows match it; teleport: not quoted, as neither source has it). "
        'Subgoal rows without "line of sight" in their '
        "label ran before `deploy.subgoals.line_of_sight` existed (the rule by skill hops alone, "
        "`line_of_sight: false`). The subgoal graph's jump rule (a window with a step longer "
        "than a cell is no edge) changes only the teleport data's graph: no other dataset has "
        f"such a step. Runs made on: {machine}.",
        "",
        f"{made}; {stamp_text(stamp)}.",
        "",
        "| dataset | agent | task 1 | task 2 | task 3 | task 4 | task 5 | overall | episodes |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        t = r["tasks"]
        cells = [_cell(t[k]) if k in t else "–" for k in TASKS]
        lines.append(f"| {r['dataset']} | {r['label']} | " + " | ".join(cells)
                     + f" | **{_cell(t[OVERALL])}** | {t[OVERALL]['episodes']} |")  # fmt: skip
    datasets = list(dict.fromkeys(r["dataset"] for r in runs))
    lines += ["", *_published_rows(datasets), "", *_verdicts(runs, datasets)]
    if not_run:
        lines += ["", "Not run yet: " + ", ".join(not_run) + "."]
    lines += ["", "Commands (in order):", "", "```bash", *commands, "```", ""]
    return "\n".join(lines)


def published_json(datasets: list[str] = DATASETS) -> dict[str, dict[str, list[int]]]:
    """OGBench's rows and the later methods' as printed (percent): dataset -> method ->
    [mean, std]."""
    out = {}
    for dataset in datasets:
        row = every_published(dataset)
        if row is not None:
            out[dataset] = {m: [round(100 * a), round(100 * b)] for m, (a, b) in row.items()}
    return out


def write(
    out: Path,
    runs: list[dict[str, Any]],
    commands: list[str],
    machine: str,
    stamp: dict[str, Any],
    not_run: list[str] = (),
) -> None:
    """`out/ogbench-point.json` (rows, commands, machines, OGBench's table) and `.md`."""
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "ogbench-point.json", {
        "machine": machine, "stamp": stamp, "runs": runs, "commands": commands,
        "not_run": list(not_run), "published": published_json(),
    })  # fmt: skip
    with atomic_path(out / "ogbench-point.md") as tmp:
        tmp.write_text(render(runs, commands, machine, stamp, not_run))


# --- the DVC pipeline (experiments/ogbench/) ----------------------------------------------------


def load_plan(vars_file: Path) -> dict[str, Any]:
    """The pipeline's vars file: `data` (the data roots' folder), `datasets` (data root ->
    its variant and overrides), `runs` (deploy run -> its root, dataset, label, ...)."""
    try:
        plan = yaml.safe_load(vars_file.read_text())
    except FileNotFoundError as exc:
        raise UserError(f"{vars_file}: not found; run from the repository root") from exc
    for key in ("data", "datasets", "runs"):
        if key not in (plan or {}):
            raise UserError(f"{vars_file}: no '{key}:'; see experiments/ogbench/params.yaml")
    return plan


def rows_path(plan: dict[str, Any], root: str, repo: Path = Path(".")) -> Path:
    return repo / plan["data"] / "rows" / f"{root}.json"


def dataset_rows(plan: dict[str, Any], root: str, repo: Path = Path(".")) -> list[dict]:
    """The rows of one data root's runs, in the vars file's order (each with its run `key`)."""
    if root not in plan["datasets"]:
        raise UserError(f"data root {root!r} is not one of {list(plan['datasets'])}")
    rows = []
    for key, run in plan["runs"].items():
        if run["root"] == root:
            folder = Path(plan["data"]) / root / "runs" / run["run"]
            row = collect_run(run["dataset"], run["label"], repo / folder)
            rows.append({"key": key, **row, "run": folder.as_posix()})
    return rows


def write_dataset_rows(plan: dict[str, Any], root: str, repo: Path = Path(".")) -> Path:
    """Stage `dataset@<root>`: its rows to `<data>/rows/<root>.json`."""
    path = rows_path(plan, root, repo)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, dataset_rows(plan, root, repo))
    return path


def report_from_rows(
    plan: dict[str, Any], repo: Path, out: Path, stamp: dict[str, Any], lock: Path
) -> dict[str, Any]:
    """Stage `report`: every data root's rows that exist, in the vars file's order, the commands
    of `lock`; roots without rows are listed as not run."""
    runs, not_run = [], []
    for root in plan["datasets"]:
        rows = read(rows_path(plan, root, repo))
        if rows is None:
            not_run.append(root)
        else:
            runs += rows
    if not runs:
        raise UserError(
            f"no rows under {repo / plan['data'] / 'rows'}; run "
            "`uv run dvc repro experiments/ogbench/dvc.yaml` (or one dataset@<root>) first"
        )
    order = list(plan["runs"])
    runs.sort(key=lambda r: order.index(r["key"]) if r.get("key") in order else len(order))
    commands = ["uv run dvc repro experiments/ogbench/dvc.yaml", "# which ran (dvc.lock):"]
    commands += lock_commands(lock)
    write(out, runs, commands, stamp["machine"], stamp, not_run)
    return {"runs": runs, "not_run": not_run}
