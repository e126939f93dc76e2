"""results/antmaze.md + results/antmaze.json: OPOSM on OGBench's ant mazes (the report itself:
`pipeline/reporting/antmaze.py`). The report stage of `experiments/antmaze/dvc.yaml` runs

    python scripts/antmaze_report.py --maze medium=data/experiments/antmaze/medium \
        [--maze large=...] --notes experiments/antmaze/notes.json \
        --lock experiments/antmaze/dvc.lock --out results

`--keep` keeps the mazes of the existing OUT/antmaze.json that no `--maze` names (a maze whose
data root is gone: another machine's run) and updates only those given.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.errors import UserError
from pipeline.reporting import antmaze
from pipeline.reporting.common import lock_commands, read, stamp

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maze", action="append", default=[], help="MAZE=DATA_ROOT (repeat)")
    parser.add_argument("--notes", type=Path, help="JSON: maze -> a list of notes on its runs")
    parser.add_argument("--lock", type=Path, help="the pipeline's dvc.lock: its commands listed")
    parser.add_argument("--out", type=Path, default=ROOT / "results")
    parser.add_argument("--keep", action="store_true",
                        help="keep OUT/antmaze.json's mazes that no --maze names")  # fmt: skip
    args = parser.parse_args(argv)
    notes = (read(args.notes) if args.notes else None) or {}
    previous = (read(args.out / "antmaze.json") if args.keep else None) or {}
    mazes = dict(previous.get("mazes", {}))
    for item in args.maze:
        name, _, root = item.partition("=")
        if name not in antmaze.MAZES or not root:
            raise UserError(
                f"--maze {item!r}: expected MAZE=DATA_ROOT, MAZE one of {antmaze.MAZES}"
            )
        mazes[name] = antmaze.collect(Path(root)) | {"notes": notes.get(name, [])}
    commands = ["uv run dvc repro experiments/antmaze/dvc.yaml"]
    if args.lock:
        commands += ["# which ran (dvc.lock):", *lock_commands(args.lock)]
    expert = antmaze.expert_info(read(ROOT / "experts" / "ant" / "actor.json") or {})
    results = antmaze.build(mazes, expert, commands, stamp(ROOT))
    antmaze.write(args.out, results)
    print(f"wrote {args.out / 'antmaze.md'} and antmaze.json")


if __name__ == "__main__":
    try:
        main()
    except UserError as exc:  # a corrupt report or a bad argument: one line, no traceback
        sys.exit(f"error: {exc}")
