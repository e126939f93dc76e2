"""results/ogbench-point.md + .json: OPOSM under OGBench's protocol on its point mazes, beside
OGBench's published table (issue 18).

Each `--run DATASET/LABEL=RUN_DIR` is one `oposm deploy` run (its `reports/deploy/report.json`) on
OGBench's five evaluation tasks (its agent: oposm, or the run's only agent, e.g. gcbc). DATASET is
the maze for its navigate dataset (`medium`, `teleport`) or the maze and `-stitch` for its stitch
dataset (`medium-stitch`). `--command` lists the commands that produced them, in order.

    uv run python scripts/ogbench_point_report.py \
        --run "medium/OPOSM + subgoals=data/ogb/medium/runs/ogb50-subgoals" \
        --run "medium/OPOSM (paper's planner)=data/ogb/medium/runs/ogb50-plain" \
        --command "uv run oposm ingest -p params-ogbench-pointmaze-medium.yaml ..."
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

from pipeline.errors import UserError
from pipeline.io import atomic_path, write_json
from stages.results_common import read

ROOT = Path(__file__).resolve().parents[1]
TASKS = [f"ogbench-task{i}" for i in range(1, 6)]
METHODS = ("GCBC", "GCIVL", "GCIQL", "QRL", "CRL", "HIQL")
# OGBench's paper, success % (mean +- std over 8 seeds). Navigate datasets: as quoted in
# docs/references.md. Stitch datasets: OGBench's table as copied by later papers (its navigate
# rows in those copies match the navigate table cell for cell); not read from the paper here.
PUBLISHED = {
    "medium": [(9, 6), (63, 6), (53, 8), (82, 5), (29, 7), (79, 5)],
    "large": [(29, 6), (45, 5), (34, 3), (86, 9), (39, 7), (58, 5)],
    "giant": [(1, 2), (0, 0), (0, 0), (68, 7), (27, 10), (46, 9)],
    "medium-stitch": [(23, 18), (70, 14), (21, 9), (80, 12), (0, 1), (74, 6)],
    "large-stitch": [(7, 5), (12, 6), (31, 2), (84, 15), (0, 0), (13, 6)],
    "giant-stitch": [(0, 0), (0, 0), (0, 0), (50, 8), (0, 0), (0, 0)],
}
# Datasets we run whose published numbers are not quoted here (docs/references.md has no teleport
# rows, and OGBench's table could not be read from this machine): reported without a verdict.
UNQUOTED = ("teleport", "teleport-stitch")
DATASETS = [*PUBLISHED, *UNQUOTED]


def collect(spec: str) -> dict:
    """`DATASET/LABEL=RUN_DIR` -> the run's numbers per task and overall (agent oposm)."""
    name, _, run = spec.partition("=")
    dataset, _, label = name.partition("/")
    if not (run and label) or dataset not in DATASETS:
        raise UserError(
            f"--run {spec!r}: expected DATASET/LABEL=RUN_DIR, DATASET one of {DATASETS}"
        )
    path = Path(run) / "reports" / "deploy" / "report.json"
    report = read(path)
    agents = list(report.get("by_agent", {}))
    agent = agents[0] if len(agents) == 1 else "oposm"  # a run of one agent: that agent
    try:
        rows = report["by_agent"][agent]
    except KeyError as exc:
        raise UserError(f"{path}: no oposm results (deploy.agents must include oposm)") from exc
    keep = ("episodes", "successes", "success_rate", "success_ci95_low", "success_ci95_high")
    out = {t: {k: rows[t][k] for k in keep} for t in [*TASKS, "ogbench"] if t in rows}
    if "ogbench" not in out:
        raise UserError(f"{path}: not a run of the ogbench tasks (deploy.tasks: [ogbench])")
    return {"dataset": dataset, "label": label, "agent": agent, "run": run,
            "env_id": report["env_id"], "max_steps": report["max_steps"],
            "success_radius": report["success_radius"], "wall_s": report.get("wall_s"),
            "tasks": out}  # fmt: skip


def _cell(row: dict) -> str:
    lo, hi = 100 * row["success_ci95_low"], 100 * row["success_ci95_high"]
    return f"{100 * row['success_rate']:.0f} ({lo:.0f}-{hi:.0f})"


def render(runs: list[dict], commands: list[str], machine: str) -> str:
    lines = [
        "# OGBench point mazes: OPOSM under OGBench's protocol, beside its published table",
        "",
        "Success (%) on OGBench's five evaluation tasks per maze (its start and goal cells with "
        "its noise, at most 1000 steps, success within 1.0 of the goal), with 95 % Wilson "
        "intervals; one trained model and one deploy seed per dataset. Dataset: the maze alone is "
        "its navigate dataset, `-stitch` its stitch dataset (both made with OGBench's recipe, "
        "smaller than OGBench's files). Published: OGBench's paper, mean +- std over 8 seeds "
        "(navigate: docs/references.md; stitch: OGBench's table as copied by later papers, whose "
        "navigate rows match it; teleport: not quoted, as neither source has it). "
        'Subgoal rows without "line of sight" in their '
        "label ran before `deploy.subgoals.line_of_sight` existed (the rule by skill hops alone, "
        "`line_of_sight: false`). The subgoal graph's jump rule (a window with a step longer "
        "than a cell is no edge) changes only the teleport data's graph: no other dataset has "
        "such a step. Machine: " + machine + ".",
        "",
        "| dataset | agent | task 1 | task 2 | task 3 | task 4 | task 5 | overall | episodes |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        t = r["tasks"]
        cells = [_cell(t[k]) if k in t else "–" for k in TASKS]
        lines.append(f"| {r['dataset']} | {r['label']} | " + " | ".join(cells)
                     + f" | **{_cell(t['ogbench'])}** | {t['ogbench']['episodes']} |")  # fmt: skip
    lines += ["", "| dataset | " + " | ".join(METHODS) + " | best published |",
              "|---|" + "---|" * (len(METHODS) + 1)]  # fmt: skip
    for dataset in dict.fromkeys(r["dataset"] for r in runs):
        if dataset not in PUBLISHED:
            lines.append(f"| {dataset} | " + " | ".join("not quoted" for _ in METHODS) + " | – |")
            continue
        published = PUBLISHED[dataset]
        best = max(range(len(METHODS)), key=lambda i: published[i][0])
        lines.append(f"| {dataset} | " + " | ".join(f"{m} +- {s}" for m, s in published)
                     + f" | {METHODS[best]} {published[best][0]} |")  # fmt: skip
    lines += [
        "",
        "Verdict per dataset (is our best run's interval above the best published mean?):",
    ]
    for dataset in dict.fromkeys(r["dataset"] for r in runs):
        ours = [r for r in runs if r["dataset"] == dataset and r["agent"] == "oposm"]
        if not ours:
            continue
        top = max(ours, key=lambda r: r["tasks"]["ogbench"]["success_rate"])
        if dataset not in PUBLISHED:
            lines.append(f"- {dataset}: {top['label']} {_cell(top['tasks']['ogbench'])}; no "
                         "published number is quoted here to compare with.")  # fmt: skip
            continue
        best_pub = max(m for m, _ in PUBLISHED[dataset])
        low = 100 * top["tasks"]["ogbench"]["success_ci95_low"]
        word = "above" if low > best_pub else "not above"
        lines.append(f"- {dataset}: {top['label']} {_cell(top['tasks']['ogbench'])} is {word} the "
                     f"best published {best_pub} %.")  # fmt: skip
    checks = [r for r in runs if r["agent"] == "gcbc" and r["dataset"] in PUBLISHED]
    if checks:
        lines += ["", "Our GCBC against OGBench's (the same agent, our implementation and sizes):"]
    for r in checks:
        mean, std = PUBLISHED[r["dataset"]][METHODS.index("GCBC")]
        lines.append(f"- {r['dataset']}: ours {_cell(r['tasks']['ogbench'])}, OGBench's "
                     f"{mean} +- {std}.")  # fmt: skip
    lines += ["", "Commands (in order):", "", "```bash", *commands, "```", ""]
    return "\n".join(lines)


def _this_machine() -> str:
    return f"{platform.machine()} CPU, {os.cpu_count()} cores"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", action="append", default=[], help="DATASET/LABEL=RUN_DIR (repeat)")
    parser.add_argument("--command", action="append", default=[], help="a command run (repeat)")
    parser.add_argument(
        "--machine", help="where the runs ran (default: this machine, or with --keep the kept one)"
    )
    parser.add_argument("--out", type=Path, default=ROOT / "results")
    parser.add_argument(
        "--keep",
        action="store_true",
        help="start from the runs and commands of the existing OUT/ogbench-point.json (their run "
        "folders may be gone); a --run with the same DATASET/LABEL replaces its row",
    )
    args = parser.parse_args()
    try:
        previous = (read(args.out / "ogbench-point.json") or {}) if args.keep else {}
        new = [collect(spec) for spec in args.run]
        labels = {(r["dataset"], r["label"]) for r in new}
        runs = [r for r in previous.get("runs", []) if (r["dataset"], r["label"]) not in labels]
        runs += new
        commands = previous.get("commands", []) + args.command
        machine = args.machine or previous.get("machine") or _this_machine()
        if not runs:
            raise UserError("give at least one --run DATASET/LABEL=RUN_DIR")
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(1)
    args.out.mkdir(parents=True, exist_ok=True)
    published = {m: dict(zip(METHODS, v, strict=True)) for m, v in PUBLISHED.items()}
    write_json(
        args.out / "ogbench-point.json",
        {"machine": machine, "runs": runs, "commands": commands, "published": published},
    )
    with atomic_path(args.out / "ogbench-point.md") as tmp:
        tmp.write_text(render(runs, commands, machine))


if __name__ == "__main__":
    main()
