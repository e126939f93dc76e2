"""results/ogbench-point.md + .json: OPOSM under OGBench's protocol on its point mazes, beside
OGBench's published table. The command line of `pipeline.reporting.ogbench_point`.

From the DVC pipeline (what `uv run dvc repro experiments/ogbench/dvc.yaml` runs):

    oposm report ogbench-point --vars experiments/ogbench/params.yaml --rows medium
    oposm report ogbench-point --vars experiments/ogbench/params.yaml --out results

(the first writes one data root's rows, `<data>/rows/medium.json`; the second the report from
every root's rows that exist.)

From run folders named one by one: each `--run DATASET/LABEL=RUN_DIR` is one `oposm deploy` run
(its `reports/deploy/report.json`) on OGBench's five evaluation tasks (its agent: oposm, or the
run's only agent, e.g. gcbc). DATASET is the maze for its navigate dataset (`medium`,
`teleport`) or the maze and `-stitch` for its stitch dataset (`medium-stitch`). `--command` lists
the commands that produced them, in order; `--keep` starts from the existing report's rows.

    uv run oposm report ogbench-point \
        --run "medium/OPOSM + subgoals=data/ogb/medium/runs/ogb50-subgoals" \
        --run "medium/OPOSM (paper's planner)=data/ogb/medium/runs/ogb50-plain" \
        --command "uv run oposm ingest -p params-ogbench-pointmaze-medium.yaml ..."
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.errors import UserError
from pipeline.reporting import ogbench_point
from pipeline.reporting.common import read, stamp

ROOT = Path(__file__).resolve().parents[1]


def _from_runs(args: argparse.Namespace) -> None:
    previous = (read(args.out / "ogbench-point.json") or {}) if args.keep else {}
    new = [ogbench_point.collect_run(*ogbench_point.parse_spec(spec)) for spec in args.run]
    labels = {(r["dataset"], r["label"]) for r in new}
    runs = [r for r in previous.get("runs", []) if (r["dataset"], r["label"]) not in labels]
    runs += new
    if not runs:
        raise UserError("give at least one --run DATASET/LABEL=RUN_DIR")
    s = stamp(Path.cwd())
    machine = args.machine or previous.get("machine") or s["machine"]
    commands = previous.get("commands", []) + args.command
    ogbench_point.write(args.out, runs, commands, machine, s)


def _from_dvc(args: argparse.Namespace) -> None:
    if args.run or args.command or args.keep:
        raise UserError("--vars takes its runs from the vars file: no --run, --command, --keep")
    plan = ogbench_point.load_plan(args.vars)
    if args.rows:
        print(f"wrote {ogbench_point.write_dataset_rows(plan, args.rows)}")
        return
    s = stamp(Path.cwd())
    if args.machine:
        s["machine"] = args.machine
    lock = Path(s["dvc"]["lock"]) if s["dvc"] else args.vars.parent / "dvc.lock"
    found = ogbench_point.report_from_rows(plan, Path("."), args.out, s, lock)
    if found["not_run"]:
        print(f"not run: {', '.join(found['not_run'])}")


def main(argv: list[str] | None = None, prog: str | None = None) -> None:
    """The command line (`oposm report ogbench-point ...`)."""
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0])
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
    parser.add_argument(
        "--vars", type=Path, help="the DVC pipeline's vars file (experiments/ogbench/params.yaml)"
    )
    parser.add_argument("--rows", metavar="ROOT", help="with --vars: write one data root's rows")
    args = parser.parse_args(argv)
    if args.vars is not None:
        _from_dvc(args)
    elif args.rows:
        raise UserError("--rows needs --vars")
    else:
        _from_runs(args)
