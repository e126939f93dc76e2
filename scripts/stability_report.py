"""`results/stability-cpu.{md,json}`: EM across seeds, per recipe (`scripts/stability_cpu.sh`).

Each `--run "RECIPE SEED RUN_DIR"` is a run folder holding `oposm train`'s `metrics/train.json`
and `oposm deploy`'s `metrics/deploy.json` (random goals). A recipe is stable on a seed when its
validation s_T NLL with prior skills is within `NLL_BAND` of the recipe's median and its
random-goal success is at least `MIN_SUCCESS`; a run not yet finished is listed as missing.

`--keep` an earlier report: a run whose folder holds no training metrics here (the data of an
earlier session, on another machine) keeps its row from that report, with the commit and the
machine it ran on, so a sweep of one recipe does not erase the others.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

from pipeline.evaluation.proportions import wilson_interval
from pipeline.io import atomic_path, write_json
from pipeline.reporting.common import percent, read, stamp, stamp_text

NLL_BAND = 0.5  # nats around the recipe's median
MIN_SUCCESS = 0.95  # random goals reached
# Recipes renamed since an earlier report: `ema` was the shipped E-step in bfloat16.
RENAMED = {"ema": "bfloat16"}


def _run(text: str) -> tuple[str, int, Path]:
    recipe, seed, folder = text.split(maxsplit=2)
    return recipe, int(seed), Path(folder)


def earlier_rows(report: dict | None) -> dict[tuple[str, int], dict]:
    """The finished rows of an earlier report by (recipe, seed), each with its commit and
    machine (a row of a report that recorded them per row keeps its own)."""
    if report is None:
        return {}
    machine = report.get("stamp", {}).get("machine")
    out = {}
    for row in report.get("runs", []):
        if "val_st_nll_prior" not in row:
            continue
        recipe = RENAMED.get(row["recipe"], row["recipe"])
        out[recipe, row["seed"]] = (
            {"commit": report.get("commit"), "machine": machine} | row | {"recipe": recipe}
        )
    return out


def _same_stamp(row: dict, earlier: dict | None) -> dict:
    """`row` with `earlier`'s commit and machine when its numbers are `earlier`'s: the same run,
    read again (a report rewritten later must not date it to its own commit)."""
    if earlier is None:
        return row
    numbers = [k for k in row if k not in ("run", "commit", "machine")]
    if all(earlier.get(k) == row[k] for k in numbers):
        return row | {"commit": earlier.get("commit"), "machine": earlier.get("machine")}
    return row


def collect(
    runs: list[tuple[str, int, Path]], stamped: dict, earlier: dict | None = None
) -> list[dict]:
    kept = earlier_rows(earlier)
    rows = []
    for recipe, seed, folder in runs:
        train, deploy = read(folder / "metrics/train.json"), read(folder / "metrics/deploy.json")
        if train is None and (recipe, seed) in kept:
            rows.append(kept[recipe, seed])
            continue
        row = {"recipe": recipe, "seed": seed, "run": str(folder)}
        if train is not None or deploy is not None:  # a row not run yet has no commit or machine
            row |= {"commit": stamped["commit"], "machine": stamped["machine"]}
        if train is not None:
            row |= {
                "published_step": train["best_step"],
                "val_st_nll_prior": train["best_val_st_nll_prior"],
                "diverged": train.get("diverged"),
                "steps_per_s": train.get("steps_per_s"),
            }
        if deploy is not None:
            for task, result in deploy["oposm"].items():
                if isinstance(result, dict) and "success" in result:
                    row |= {f"{task}_success": result["success"], f"{task}_episodes":
                            result["episodes"]}  # fmt: skip
        rows.append(_same_stamp(row, kept.get((recipe, seed))))
    for recipe in {r["recipe"] for r in rows}:
        mine = [r for r in rows if r["recipe"] == recipe and "val_st_nll_prior" in r]
        median = statistics.median(r["val_st_nll_prior"] for r in mine) if mine else None
        for r in mine:
            if "random_goal_success" in r:
                r["stable"] = bool(
                    abs(r["val_st_nll_prior"] - median) <= NLL_BAND
                    and r["random_goal_success"] >= MIN_SUCCESS
                )
    return rows


def _success(row: dict, task: str) -> str:
    """`k/n` with its Wilson interval, or empty."""
    if f"{task}_success" not in row:
        return ""
    n = row[f"{task}_episodes"]
    k = round(row[f"{task}_success"] * n)
    return f"{percent(k / n, *wilson_interval(k, n), digits=0)}, {k}/{n}"


def markdown(rows: list[dict], stamped: dict) -> str:
    lines = [
        "# EM across seeds: every run trained and deployed",
        "",
        "Written by `scripts/stability_report.py` (numbers: `stability-cpu.json`); "
        f"{stamp_text(stamped)}.",
        "",
        "Command: `bash scripts/stability_cpu.sh` (two runs at a time, or one with `--jobs 1`; "
        "one torch thread each; "
        "the main job's params, 5000 steps; deploy: the main job's 100 random goals "
        "and 100 corner-to-corner episodes); `bash scripts/stability_cpu.sh [--seeds 0,3] "
        "RECIPE...` reruns some recipes or seeds, the others keep their rows (and their commit "
        "and machine, in the last table) from the committed report. A run is stable when its "
        "validation s_T NLL with "
        f"prior skills is within {NLL_BAND} of its recipe's median and it reaches at least "
        f"{MIN_SUCCESS:.0%} of the random goals. Recipes: default = the shipped params "
        "(the conv posterior, `train.encoder: conv`, not the paper's; the subgoal graph once an "
        "episode is stuck, `deploy.subgoals.patience: 2`; `train.e_prior: ema`, float32; OPOSM "
        "replans every 20 steps), which trains as conv does, so its first columns repeat conv's; "
        "conv = the default's training deployed without the subgoal graph "
        "(`deploy.subgoals.enabled: false`); gru = the default before (the paper's GRU "
        "posterior, `train.encoder: gru`, and no subgoal graph; its rows were named default); "
        "tau39 = gru's models deployed as gru did before (each skill run whole, "
        "`deploy.replan_every: null`, T = 39 steps), so its first columns repeat gru's; "
        "tau10 = the same replanning every 10 steps with 10 CEM iterations (instead of 20); the "
        "rows of the recipes below were deployed as tau39 (their commits, in the last table, "
        "predate the change); bfloat16 = gru's training with `train.dtype: bfloat16` "
        "(the earlier rows named ema); paper = `train.e_prior: current` (the paper's E-step and "
        "an earlier default; its earlier runs, on another CPU and code version: "
        "`git show ad9de92:results/stability-cpu.md`); censored and layernorm = the paper's "
        "E-step with `train.action_likelihood: censored` or `train.policy_trunk: "
        "layernorm_silu`; subgoals = gru's models (the same training, so its first columns "
        "repeat gru's) deployed with the subgoal graph from the first replan "
        "(`deploy.subgoals.patience: null`), subgoals3 the same with waypoints up to 3 skills "
        "ahead (`deploy.subgoals.reach: 3`).",
        "",
        "| recipe | seed | published step | val s_T NLL, prior skills | diverged | random_goal, % "
        "(Wilson 95 %) | corners | stable |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "val_st_nll_prior" not in r:
            lines.append(f"| {r['recipe']} | {r['seed']} | not run yet | | | | | |")
            continue
        stable = {True: "yes", False: "no"}.get(r.get("stable"), "")
        lines.append(
            f"| {r['recipe']} | {r['seed']} | {r['published_step']} | "
            f"{r['val_st_nll_prior']:.3f} | {r.get('diverged')} | "
            f"{_success(r, 'random_goal')} | {_success(r, 'corners')} | {stable} |"
        )
    lines += ["", "| recipe | runs finished | stable | commit | machine |", "|---|---|---|---|---|"]
    for recipe in dict.fromkeys(r["recipe"] for r in rows):
        mine = [r for r in rows if r["recipe"] == recipe]
        done = [r for r in mine if "stable" in r]
        where = dict.fromkeys((r.get("commit"), r.get("machine")) for r in done)
        commits = ", ".join(str(c) for c in dict.fromkeys(c for c, _ in where))
        machines = "; ".join(m or "not recorded" for m in dict.fromkeys(m for _, m in where))
        lines.append(
            f"| {recipe} | {len(done)} of {len(mine)} | {sum(r['stable'] for r in done)} | "
            f"{commits} | {machines} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", action="append", default=[], help="'RECIPE SEED RUN_DIR'")
    parser.add_argument("--out", type=Path, required=True, help="results/<name> (no suffix)")
    parser.add_argument("--keep", type=Path, help="an earlier report's JSON (rows not rerun here)")
    args = parser.parse_args()
    stamped = stamp(Path.cwd())
    earlier = read(args.keep) if args.keep else None
    rows = collect([_run(text) for text in args.run], stamped, earlier)
    write_json(args.out.with_suffix(".json"), {"commit": stamped["commit"], "stamp": stamped,
                                               "runs": rows})  # fmt: skip
    with atomic_path(args.out.with_suffix(".md")) as tmp:
        tmp.write_text(markdown(rows, stamped))


if __name__ == "__main__":
    main()
