"""The results stage's experiments 2 and 4: EM vs naive VI, and model selection.

Experiment 2 (`em_vi` in experiments/params.yaml): per dataset (the plain maze, the maze with
random pushes), method (em, vi) and seed, the run `<root>/runs/<method>-seed<seed>/` holds the
validate report (the TAWM against real open-loop outcomes of prior skills) and the deploy report
(OPOSM's success and optimism gap); `pipeline.reporting.em_vi` reads them, judges the paper's
predictions once all seeds ran and draws the tables (the ant's table 3 uses it too).

Experiment 4: each EM run keeps its best checkpoint by the posterior s_T NLL (published, deployed
by experiment 2) and by the prior-marginal s_T NLL (`models/<name>/by/st_nll_prior/`), deployed
on the same episodes into `<root>/runs/em-seed<seed>-by-prior/`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.reporting import em_vi as runs_of
from pipeline.reporting.common import cell, points, read, versus

MODEL = "models/pointmaze-medium"
em_vi_tables = runs_of.tables  # the results page's name for it


def em_vi(exp: dict[str, Any], repo: Path) -> tuple[dict[str, Any], list[dict[str, Any]], int]:
    """Per dataset tag and method, each finished seed's numbers; the claims on every dataset
    whose runs all finished; and how many runs finished."""
    cfg = exp.get("em_vi")
    if not cfg:
        return {}, [], 0
    table: dict[str, Any] = {}
    found_claims: list[dict[str, Any]] = []
    done = 0
    for dataset in cfg["datasets"]:
        runs = {}
        for method in runs_of.METHODS:
            found = {}
            for seed in cfg["seeds"]:
                run = runs_of.run_numbers(repo / dataset["root"] / f"runs/{method}-seed{seed}")
                if run is not None:
                    found[str(seed)] = run
            runs[method] = found
            done += len(found)
        table[dataset["tag"]] = runs
        if all(len(runs[m]) == len(cfg["seeds"]) >= runs_of.MIN_SEEDS for m in runs_of.METHODS):
            found_claims += runs_of.claims(dataset["tag"], runs["em"], runs["vi"])
    return table, found_claims, done


def _checkpoint_step(model_dir: Path) -> int | None:
    meta = read(model_dir / "config.json")
    return None if meta is None else meta.get("step")


def selection(exp: dict[str, Any], repo: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Per dataset tag and seed: the step each criterion picked and OPOSM's success with it;
    the claim that picking by the prior-marginal NLL deploys better, per dataset, all seeds."""
    cfg = exp.get("em_vi")
    if not cfg:
        return {}, []
    table: dict[str, Any] = {}
    claims = []
    for dataset in cfg["datasets"]:
        rows = {}
        for seed in cfg["seeds"]:
            runs = repo / dataset["root"] / "runs"
            posterior = read(runs / f"em-seed{seed}/reports/deploy/report.json")
            prior = read(runs / f"em-seed{seed}-by-prior/reports/deploy/report.json")
            if posterior is None or prior is None:
                continue
            by = runs / f"em-seed{seed}" / MODEL / "by"
            rows[str(seed)] = {
                "step_by_st_nll": _checkpoint_step(by / "st_nll"),
                "step_by_st_nll_prior": _checkpoint_step(by / "st_nll_prior"),
                "by_st_nll": runs_of.deploy_numbers(posterior),
                "by_st_nll_prior": runs_of.deploy_numbers(prior),
            }
        table[dataset["tag"]] = rows
        if len(rows) == len(cfg["seeds"]) >= 3:
            prior_pool = runs_of.pooled_success({k: r["by_st_nll_prior"] for k, r in rows.items()})
            post_pool = runs_of.pooled_success({k: r["by_st_nll"] for k, r in rows.items()})
            verdict, interval = versus(prior_pool, post_pool)
            same = sum(r["step_by_st_nll"] == r["step_by_st_nll_prior"] for r in rows.values())
            claims.append({
                "claim": f"On the {dataset['tag']} maze, the checkpoint with the best "
                "prior-marginal s_T NLL deploys better than the one with the best posterior "
                "s_T NLL (EM)",
                "verdict": verdict,
                "numbers": f"by prior {cell(prior_pool)} vs by posterior {cell(post_pool)} % "
                f"(seeds pooled; {same} of {len(rows)} seeds picked the same step); "
                f"difference {points(interval)} points",
            })  # fmt: skip
    return table, claims


def selection_tables(table: dict[str, Any]) -> list[str]:
    rows = [
        "| data | seed | step by posterior NLL | success | step by prior NLL | success |",
        "|---|---|---|---|---|---|",
    ]
    for tag, seeds in table.items():
        for seed, r in seeds.items():
            rows.append(
                f"| {tag} | {seed} | {r['step_by_st_nll']} | {cell(r['by_st_nll']['success'])} "
                f"| {r['step_by_st_nll_prior']} | {cell(r['by_st_nll_prior']['success'])} |"
            )
    return rows if len(rows) > 2 else ["Not run yet."]


def _mean(values: list[float]) -> float | None:
    return sum(values) / len(values) if values else None


def plot_rows(table: dict[str, Any]) -> dict[str, list[dict[str, Any]]]:
    """CSVs of the plots: TAWM error vs horizon (k prior skills) per dataset and method, mean
    over seeds; the optimism gap per dataset and method, mean over seeds."""
    columns: dict[str, list[list[float]]] = {}
    gaps = []
    for tag, methods in table.items():
        for method, runs in methods.items():
            if not runs:
                continue
            columns[f"{tag}_{method}"] = [r["tawm_error_by_skills"] for r in runs.values()]
            gap = _mean(runs_of.values(runs, "optimism_gap_m"))
            if gap is not None:
                gaps.append({"run": f"{tag} {method}", "optimism_gap_m": round(gap, 4)})
    depth = min((len(e) for runs in columns.values() for e in runs), default=0)
    error_rows = []
    for k in range(depth):
        row: dict[str, Any] = {"skills": k + 1}
        for column, runs in columns.items():
            row[column] = round(sum(e[k] for e in runs) / len(runs), 4)
        error_rows.append(row)
    return {"em_vi_error.csv": error_rows, "optimism_gap.csv": gaps}
