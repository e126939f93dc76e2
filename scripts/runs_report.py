"""A results report of training and deploy runs: `results/<name>.md` + `.json`. It is used for
`results/precision-cpu` (bfloat16 against float32, issue 16; `scripts/precision_cpu.sh`) and
`results/stability-cpu` (EM across seeds; `scripts/stability_cpu.sh`).

Each `--train LABEL=FILE` is an `oposm train` run's `metrics/train.json`; each
`--deploy LABEL=RUN_DIR` an `oposm deploy` run (its `reports/deploy/episodes.json`); each
`--pair "A|B"` compares two deploys episode by episode (they must hold the same episodes: the
same seeds and goals). `--command` lists the commands that produced them, in order.

    uv run python scripts/runs_report.py --title "bfloat16 against float32" \\
        --train "float32, seed 0=metrics/train.json" \\
        --train "bfloat16, seed 0=data/runs/s9-train-bf16-s0/metrics/train.json" \\
        --deploy "float32 model=data/runs/s9-deploy-main-float32" \\
        --deploy "bfloat16 model=data/runs/s9-train-bf16-s0" \\
        --pair "float32 model|bfloat16 model" --command "uv run oposm train ..." \\
        --out results/precision-cpu
"""

from __future__ import annotations

import argparse
import sys
from datetime import date
from pathlib import Path

from scipy.stats import binomtest

from pipeline.errors import UserError
from pipeline.evaluation.proportions import difference_interval
from pipeline.io import atomic_path, write_json
from pipeline.reporting.common import cell, machine, rate, read, stamp, stamp_text

ROOT = Path(__file__).resolve().parents[1]
TRAIN_KEYS = ("best_step", "best_val_st_nll_prior", "best_val_st_nll", "val_action_nll",
              "steps_per_s", "wall_s")  # fmt: skip


def _labelled(text: str, what: str) -> tuple[str, Path]:
    label, sep, path = text.partition("=")
    if not sep or not label.strip() or not path.strip():
        raise UserError(f"{what} takes LABEL=PATH, got {text!r}")
    return label.strip(), Path(path.strip())


def _read_json(path: Path) -> object:
    """`path`'s JSON (`pipeline.reporting.common.read`); a missing file is a `UserError` too."""
    data = read(path)
    if data is None:
        raise UserError(f"{path} does not exist; run the command that writes it first")
    return data


def _episodes(run_dir: Path) -> dict[tuple[str, int], dict]:
    path = run_dir / "reports" / "deploy" / "episodes.json"
    episodes = _read_json(path)
    if not isinstance(episodes, list) or not episodes:
        raise UserError(f"{path} holds no episodes; rerun `oposm deploy`")
    return {(e["task"], e["episode"]): e for e in episodes if e["agent"] == "oposm"}


def success_rows(episodes: dict[tuple[str, int], dict]) -> dict[str, dict]:
    """Per task and over all: successes, episodes, the rate and its Wilson interval (`rate`)."""
    out = {}
    for task in [*sorted({t for t, _ in episodes}), "all"]:
        chosen = [e for (t, _), e in episodes.items() if task in ("all", t)]
        out[task] = rate(sum(bool(e["success"]) for e in chosen), len(chosen))
    return out


def paired(a: dict[tuple[str, int], dict], b: dict[tuple[str, int], dict]) -> dict[str, dict]:
    """Episode-by-episode comparison of two deploys on the same episodes, per task and over all:
    successes of each, episodes only one of them solved, the exact McNemar test's p (a binomial
    test on those), and the Newcombe interval of the difference a - b (it ignores the pairing,
    so it is conservative).

    Raises:
        UserError: the two runs do not hold the same episodes (seeds, starts and goals).
    """
    if a.keys() != b.keys() or any(
        a[k]["seed"] != b[k]["seed"] or a[k]["goal"] != b[k]["goal"] for k in a
    ):
        raise UserError("the two deploys of a --pair hold different episodes; rerun both with "
                        "the same deploy.tasks, deploy.episodes and seeds")  # fmt: skip
    out = {}
    for task in [*sorted({t for t, _ in a}), "all"]:
        keys = [k for k in a if task in ("all", k[0])]
        wins_a = sum(bool(a[k]["success"]) for k in keys)
        wins_b = sum(bool(b[k]["success"]) for k in keys)
        only_a = sum(bool(a[k]["success"]) and not b[k]["success"] for k in keys)
        only_b = sum(bool(b[k]["success"]) and not a[k]["success"] for k in keys)
        p = binomtest(only_a, only_a + only_b).pvalue if only_a + only_b else 1.0
        low, high = difference_interval(wins_a, len(keys), wins_b, len(keys))
        out[task] = {"episodes": len(keys), "successes": [wins_a, wins_b], "only_first": only_a,
                     "only_second": only_b, "mcnemar_p": p,
                     "difference": (wins_a - wins_b) / len(keys),
                     "difference_interval": [low, high]}  # fmt: skip
    return out


def this_machine() -> str:
    """This machine (`pipeline.reporting.common.machine`: the CPU model and whether it multiplies
    bfloat16 natively, cores, GPUs, torch) and today's date."""
    return f"{machine()}; report written {date.today().isoformat()}"


def markdown(report: dict) -> str:
    lines = [
        f"# {report['title']}",
        "",
        f"Written by `scripts/runs_report.py` (numbers: `{report['name']}.json`). "
        f"Machine: {report['machine']}."
        + (f" Report {stamp_text(report['stamp'])}." if report.get("stamp") else ""),
        "",
        *[f"{p}\n" for p in report["intro"]],
        "Commands, in order:",
        "",
        *[f"- `{c}`" for c in report["commands"]],
        "",
    ]
    if report["train"]:
        lines += [
            "## Training runs",
            "",
            "Validation numbers of the published checkpoint (`train.select: st_nll_prior`, the "
            "s_T NLL with skills drawn from the prior) and the best s_T NLL under the posterior "
            "skill; lower is better. The wall time depends on what else ran (see the commands).",
            "",
            "| run | published step | val s_T NLL, prior skills | best val s_T NLL | "
            "val action NLL | steps/s | wall s |",
            "|---|---|---|---|---|---|---|",
        ]
        for label, m in report["train"].items():
            lines.append(
                f"| {label} | {m['best_step']} | {m['best_val_st_nll_prior']:.3f} | "
                f"{m['best_val_st_nll']:.3f} | {m['val_action_nll']:.3f} | "
                f"{m['steps_per_s']:.1f} | {m['wall_s']:.0f} |"
            )
        lines.append("")
    if report["deploy"]:
        tasks = [t for t in next(iter(report["deploy"].values())) if t != "all"]
        lines += [
            "## Deploys: success within 0.5 m (%, Wilson 95 % interval)",
            "",
            "| deploy | " + " | ".join(tasks) + " | all |",
            "|---|" + "---|" * (len(tasks) + 1),
        ]
        for label, rows in report["deploy"].items():
            cells = [
                f"{cell(r)}, {r['successes']}/{r['episodes']}"
                for r in (rows[t] for t in [*tasks, "all"])
            ]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        lines.append("")
    if report["pairs"]:
        lines += [
            "## Paired: the same episodes, episode by episode",
            "",
            "Episodes only one of the two solved, the exact McNemar test on them, and the "
            "difference first - second in points with its Newcombe 95 % interval (which "
            "ignores the pairing, so it is wider than needed).",
            "",
            "| first | second | task | successes | only first | only second | McNemar p | "
            "difference |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for pair in report["pairs"]:
            for task, r in pair["tasks"].items():
                low, high = r["difference_interval"]
                lines.append(
                    f"| {pair['first']} | {pair['second']} | {task} | "
                    f"{r['successes'][0]} vs {r['successes'][1]} of {r['episodes']} | "
                    f"{r['only_first']} | {r['only_second']} | {r['mcnemar_p']:.2f} | "
                    f"{100 * r['difference']:+.1f} [{100 * low:+.1f}, {100 * high:+.1f}] |"
                )
        lines.append("")
    lines += [f"{n}" for n in report["notes"]]
    return "\n".join(lines).rstrip() + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", action="append", default=[], help="LABEL=metrics/train.json")
    parser.add_argument("--deploy", action="append", default=[], help="LABEL=deploy run dir")
    parser.add_argument("--pair", action="append", default=[], help="'LABEL A|LABEL B'")
    parser.add_argument("--command", action="append", default=[])
    parser.add_argument("--title", required=True, help="the report's heading")
    parser.add_argument("--intro", action="append", default=[], help="a paragraph at the top")
    parser.add_argument("--note", action="append", default=[], help="a paragraph at the end")
    parser.add_argument(
        "--machine",
        default=None,
        help="where the runs ran (default: this "
        "machine's CPU, its AVX512-BF16 flag, cores and torch; today's date)",
    )
    parser.add_argument(
        "--out", type=Path, required=True, help="results/<name> (writes <name>.md and <name>.json)"
    )
    args = parser.parse_args(argv)
    try:
        train = {}
        for text in args.train:
            label, path = _labelled(text, "--train")
            metrics = _read_json(path)
            train[label] = {k: metrics[k] for k in TRAIN_KEYS}
        episodes = dict(_labelled(t, "--deploy") for t in args.deploy)
        loaded = {label: _episodes(path) for label, path in episodes.items()}
        pairs = []
        for text in args.pair:
            first, sep, second = (s.strip() for s in text.partition("|"))
            if not sep or first not in loaded or second not in loaded:
                raise UserError(f"--pair takes 'A|B' of two --deploy labels, got {text!r}")
            pairs.append({"first": first, "second": second,
                          "tasks": paired(loaded[first], loaded[second])})  # fmt: skip
        report = {
            "title": args.title,
            "name": args.out.name,
            "intro": args.intro,
            "machine": args.machine or this_machine(),
            "stamp": stamp(ROOT),
            "commands": args.command,
            "train": train,
            "deploy": {label: success_rows(e) for label, e in loaded.items()},
            "pairs": pairs,
            "notes": args.note,
        }
    except UserError as exc:
        sys.exit(f"error: {exc}")
    write_json(args.out.with_suffix(".json"), report)
    with atomic_path(args.out.with_suffix(".md")) as tmp:
        tmp.write_text(markdown(report))
    print(f"wrote {args.out.with_suffix('.md')} and .json")


if __name__ == "__main__":
    main()
