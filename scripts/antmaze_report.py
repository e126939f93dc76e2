"""The ant mazes' reports (`pipeline/reporting/antmaze.py`), as the stages of
`experiments/antmaze/dvc.yaml` run them:

    # one maze's report, from its data root:
    python scripts/antmaze_report.py maze large data/experiments/antmaze/large \
        --notes experiments/antmaze/notes.json --lock experiments/antmaze/dvc.lock \
        --out results/antmaze/large.json
    # the page, results/antmaze.md + .json, from the mazes' reports:
    python scripts/antmaze_report.py page results/antmaze/large.json [...] --out results
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.errors import UserError
from pipeline.reporting import antmaze
from pipeline.reporting.common import lock_commands, read, stamp

ROOT = Path(__file__).resolve().parents[1]
PIPELINE = "uv run dvc repro experiments/antmaze/dvc.yaml"


def _maze(args: argparse.Namespace) -> None:
    notes = (read(args.notes) if args.notes else None) or {}
    commands = [f"{PIPELINE}:maze@{args.name}"]
    if args.lock:
        ran = [c for c in lock_commands(args.lock) if c.endswith(f"@{args.name}")]
        commands += ["# which ran (dvc.lock):", *ran]
    report = antmaze.maze_report(
        args.name, args.root, notes.get(args.name, []), commands, stamp(ROOT)
    )
    antmaze.write_maze(args.out, report)
    print(f"wrote {args.out}")


def _page(args: argparse.Namespace) -> None:
    reports = []
    for path in args.reports:
        report = read(path)
        if report is None:
            raise UserError(f"{path} does not exist; run its stage (maze@<maze>) first")
        reports.append(report)
    expert = antmaze.expert_info(read(ROOT / "experts" / "ant" / "actor.json") or {})
    antmaze.write_page(args.out, antmaze.page(reports, expert, stamp(ROOT)))
    print(f"wrote {args.out / 'antmaze.md'} and antmaze.json")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    maze = sub.add_parser("maze", help="one maze's report from its data root")
    maze.add_argument("name", help=f"one of {', '.join(antmaze.MAZES)}")
    maze.add_argument("root", type=Path, help="its data root")
    maze.add_argument("--notes", type=Path, help="JSON: maze -> a list of notes on its runs")
    maze.add_argument("--lock", type=Path, help="the pipeline's dvc.lock: its commands listed")
    maze.add_argument("--out", type=Path, required=True, help="the report's JSON file")
    page = sub.add_parser("page", help="results/antmaze.md + .json from the mazes' reports")
    page.add_argument("reports", type=Path, nargs="+", help="results/antmaze/<maze>.json files")
    page.add_argument("--out", type=Path, default=ROOT / "results")
    args = parser.parse_args(argv)
    (_maze if args.command == "maze" else _page)(args)


if __name__ == "__main__":
    try:
        main()
    except UserError as exc:  # a corrupt report or a bad argument: one line, no traceback
        sys.exit(f"error: {exc}")
