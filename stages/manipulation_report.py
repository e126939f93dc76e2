"""The manipulation datasets' reports (`pipeline/reporting/manipulation.py`), as the stages of
`experiments/manipulation/dvc.yaml` run them:

    # one dataset's report, from its data root:
    oposm report manipulation dataset cube-single-play \
        data/experiments/manipulation/cube-single-play \
        --notes experiments/manipulation/notes/cube-single-play.json \
        --lock experiments/manipulation/dvc.lock \
        --out results/manipulation/cube-single-play.json
    # one dataset's ladder (where object moves fail), from its data root:
    oposm report manipulation ladder cube-double-play \
        data/experiments/manipulation/cube-double-play \
        --out results/manipulation/cube-double-play-ladder.json
    # one variant of OPOSM on a dataset (its run folder runs/<run>/), from the data root:
    oposm report manipulation variant cube-double-play \
        data/experiments/manipulation/cube-double-play --run z256 --label "oposm z256" \
        --what "OPOSM at the paper's model sizes" --settings "-S train.z_dim=256 ..." \
        --out results/manipulation/cube-double-play-z256.json
    # the page, results/manipulation.md + .json, from the datasets' reports, ladders, variants:
    oposm report manipulation page results/manipulation/<dataset>.json ... \
        --ladders results/manipulation/cube-double-play-ladder.json \
        --variants results/manipulation/cube-double-play-z256.json --out results
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.errors import UserError
from pipeline.reporting import manipulation, manipulation_ladder, manipulation_variant
from pipeline.reporting.common import lock_commands, read, read_all, stamp

ROOT = Path(__file__).resolve().parents[1]
PIPELINE = "uv run dvc repro experiments/manipulation/dvc.yaml"


def _dataset(args: argparse.Namespace) -> None:
    notes = (read(args.notes) if args.notes else None) or []
    if not isinstance(notes, list) or not all(isinstance(n, str) for n in notes):
        raise UserError(f"{args.notes}: expected a JSON list of notes (strings) on {args.name}")
    commands = [f"{PIPELINE}:dataset@{args.name}"]
    if args.lock:
        ran = [c for c in lock_commands(args.lock) if c.endswith(f"@{args.name}")]
        commands += ["# which ran (dvc.lock):", *ran]
    report = manipulation.dataset_report(args.name, args.root, notes, commands, stamp(ROOT))
    manipulation.write_dataset(args.out, report)
    print(f"wrote {args.out}")


def _ladder(args: argparse.Namespace) -> None:
    report = manipulation_ladder.ladder_report(args.name, args.root, stamp(ROOT))
    manipulation.write_dataset(args.out, report)
    print(f"wrote {args.out}")


def _variant(args: argparse.Namespace) -> None:
    report = manipulation_variant.variant_report(
        args.name, args.root, args.run, args.label, args.what, args.settings, stamp(ROOT)
    )
    manipulation.write_dataset(args.out, report)
    print(f"wrote {args.out}")


def _page(args: argparse.Namespace) -> None:
    reports = read_all(args.reports, "dataset@<dataset>")
    ladders = read_all(args.ladders, "ladder@<dataset>")
    variants = read_all(args.variants, "variant@<dataset>")
    results = manipulation.page(reports, stamp(ROOT), ladders, variants)
    manipulation.write_page(args.out, results)
    print(f"wrote {args.out / 'manipulation.md'} and manipulation.json")


def main(argv: list[str] | None = None, prog: str | None = None) -> None:
    """The command line (`oposm report manipulation ...`): `argv`, its subcommand first."""
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    one = sub.add_parser("dataset", help="one dataset's report from its data root")
    one.add_argument("name", help=f"one of {', '.join(manipulation.DATASETS)}")
    one.add_argument("root", type=Path, help="its data root")
    one.add_argument("--notes", type=Path, help="JSON: a list of notes on its runs")
    one.add_argument("--lock", type=Path, help="the pipeline's dvc.lock: its commands listed")
    one.add_argument("--out", type=Path, required=True, help="the report's JSON file")
    ladder = sub.add_parser("ladder", help="one dataset's ladder from its data root")
    ladder.add_argument("name", help=f"one of {', '.join(manipulation.DATASETS)}")
    ladder.add_argument("root", type=Path, help="its data root")
    ladder.add_argument("--out", type=Path, required=True, help="the ladder's JSON file")
    variant = sub.add_parser("variant", help="one variant of OPOSM on a dataset")
    variant.add_argument("name", help=f"one of {', '.join(manipulation.DATASETS)}")
    variant.add_argument("root", type=Path, help="its data root")
    variant.add_argument("--run", required=True, help="the variant's run folder, runs/<run>/")
    variant.add_argument("--label", required=True, help="its row's name on the page")
    variant.add_argument("--what", required=True, help="what it changes, for its verdicts")
    variant.add_argument("--settings", required=True, help="the overrides it ran with")
    variant.add_argument("--out", type=Path, required=True, help="the variant's JSON file")
    page = sub.add_parser("page", help="results/manipulation.md + .json from the datasets' reports")
    page.add_argument("reports", type=Path, nargs="+", help="results/manipulation/<dataset>.json")
    page.add_argument("--ladders", type=Path, nargs="*", default=[],
                      help="results/manipulation/<dataset>-ladder.json")  # fmt: skip
    page.add_argument("--variants", type=Path, nargs="*", default=[],
                      help="results/manipulation/<key>.json of variant@<key>")  # fmt: skip
    page.add_argument("--out", type=Path, default=ROOT / "results")
    args = parser.parse_args(argv)
    {"dataset": _dataset, "ladder": _ladder, "variant": _variant, "page": _page}[args.command](args)
