"""The ant mazes' reports (`pipeline/reporting/antmaze.py`), as the stages of
`experiments/antmaze/dvc.yaml` run them:

    # one maze's report, from its data root:
    oposm report antmaze maze large data/experiments/antmaze/large \
        --notes experiments/antmaze/notes.json --lock experiments/antmaze/dvc.lock \
        --out results/antmaze/large.json
    # a maze's mass sweep (paper figure 5), from the runs mass<...> of its data root:
    oposm report antmaze figure5 large data/experiments/antmaze/large \
        --lock experiments/antmaze/dvc.lock --out results/antmaze/large-figure5.json
    # a maze's table 3 (EM against naive VI), from the runs table3-<method>-seed<seed>:
    oposm report antmaze table3 large data/experiments/antmaze/large \
        --e-kl closed_form --lock experiments/antmaze/dvc.lock \
        --out results/antmaze/large-table3.json
    # the page, results/antmaze.md + .json, from the mazes' reports:
    oposm report antmaze page results/antmaze/large.json [...] \
        [--figure5 results/antmaze/large-figure5.json ...] \
        [--table3 results/antmaze/large-table3.json ...] --out results
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.reporting import antmaze
from pipeline.reporting.common import lock_commands, read, read_all, stamp

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


def _figure5(args: argparse.Namespace) -> None:
    commands = [f"{PIPELINE}:figure5"]
    if args.lock:
        ran = [c for c in lock_commands(args.lock) if "--run mass" in c and f"/{args.name} " in c]
        commands += ["# which ran (dvc.lock):", *ran]
    report = antmaze.figure5_report(args.name, args.root, commands, stamp(ROOT))
    antmaze.write_maze(args.out, report)
    print(f"wrote {args.out}")


def _table3(args: argparse.Namespace) -> None:
    commands = [f"{PIPELINE}:table3"]
    if args.lock:
        ran = [c for c in lock_commands(args.lock)
               if "--run table3-" in c and f"/{args.name} " in c]  # fmt: skip
        commands += ["# which ran (dvc.lock):", *ran]
    report = antmaze.table3_report(args.name, args.root, args.e_kl, commands, stamp(ROOT))
    antmaze.write_maze(args.out, report)
    print(f"wrote {args.out}")


def _page(args: argparse.Namespace) -> None:
    reports = read_all(args.reports, "maze@<maze>")
    sweeps = read_all(args.figure5, "figure5")
    tables = read_all(args.table3, "table3")
    expert = antmaze.expert_info(read(ROOT / "experts" / "ant" / "actor.json") or {})
    antmaze.write_page(args.out, antmaze.page(reports, expert, stamp(ROOT), sweeps, tables))
    print(f"wrote {args.out / 'antmaze.md'} and antmaze.json")


def main(argv: list[str] | None = None, prog: str | None = None) -> None:
    """The command line (`oposm report antmaze ...`): `argv`, its subcommand first."""
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    maze = sub.add_parser("maze", help="one maze's report from its data root")
    maze.add_argument("name", help=f"one of {', '.join(antmaze.MAZES)}")
    maze.add_argument("root", type=Path, help="its data root")
    maze.add_argument("--notes", type=Path, help="JSON: maze -> a list of notes on its runs")
    maze.add_argument("--lock", type=Path, help="the pipeline's dvc.lock: its commands listed")
    maze.add_argument("--out", type=Path, required=True, help="the report's JSON file")
    fig5 = sub.add_parser("figure5", help="a maze's mass sweep (paper figure 5) from its root")
    fig5.add_argument("name", help=f"one of {', '.join(antmaze.MAZES)}")
    fig5.add_argument("root", type=Path, help="its data root (runs/mass<...>/)")
    fig5.add_argument("--lock", type=Path, help="the pipeline's dvc.lock: its commands listed")
    fig5.add_argument("--out", type=Path, required=True, help="the report's JSON file")
    table3 = sub.add_parser("table3", help="a maze's table 3 (EM vs naive VI) from its root")
    table3.add_argument("name", help=f"one of {', '.join(antmaze.MAZES)}")
    table3.add_argument("root", type=Path, help="its data root (runs/table3-<method>-seed<seed>/)")
    table3.add_argument("--e-kl", required=True, help="the E-step KL both methods ran (train.e_kl)")
    table3.add_argument("--lock", type=Path, help="the pipeline's dvc.lock: its commands listed")
    table3.add_argument("--out", type=Path, required=True, help="the report's JSON file")
    page = sub.add_parser("page", help="results/antmaze.md + .json from the mazes' reports")
    page.add_argument("reports", type=Path, nargs="+", help="results/antmaze/<maze>.json files")
    page.add_argument("--figure5", type=Path, nargs="*", default=[],
                      help="results/antmaze/<maze>-figure5.json files")  # fmt: skip
    page.add_argument("--table3", type=Path, nargs="*", default=[],
                      help="results/antmaze/<maze>-table3.json files")  # fmt: skip
    page.add_argument("--out", type=Path, default=ROOT / "results")
    args = parser.parse_args(argv)
    {"maze": _maze, "figure5": _figure5, "table3": _table3, "page": _page}[args.command](args)
