"""The results stage's experiments 2 and 4: EM vs naive VI, and model selection.

Experiment 2 (`em_vi` in experiments/params.yaml): per dataset (the plain maze, the maze with
random pushes), method (em, vi) and seed, the run `<root>/runs/<method>-seed<seed>/` holds the
validate report (the TAWM against real open-loop outcomes of prior skills) and the deploy report
(OPOSM's success and optimism gap). Per-seed values are compared with `separated` (all seeds of
one method beyond all of the other's), success rates pooled over seeds with Newcombe intervals.

Experiment 4: each EM run keeps its best checkpoint by the posterior s_T NLL (published, deployed
by experiment 2) and by the prior-marginal s_T NLL (`models/<name>/by/st_nll_prior/`), deployed
on the same episodes into `<root>/runs/em-seed<seed>-by-prior/`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.reporting.common import cell, pct, points, pooled, rate, read, separated, versus

METHODS = ("em", "vi")
MODEL = "models/pointmaze-medium"


def _deploy_numbers(deploy: dict[str, Any]) -> dict[str, Any]:
    oposm = deploy["by_agent"]["oposm"]
    wins = sum(oposm[t]["successes"] for t in deploy["tasks"])
    n = sum(oposm[t]["episodes"] for t in deploy["tasks"])
    gaps = [g["distance_gap_m"]["mean"] for g in (oposm.get("optimism_gap") or {}).values()]
    gaps = [g for g in gaps if g is not None]
    return {"success": rate(wins, n), "optimism_gap_m": sum(gaps) / len(gaps) if gaps else None}


def _run(root: Path) -> dict[str, Any] | None:
    validate = read(root / "reports/validate/report.json")
    deploy = read(root / "reports/deploy/report.json")
    if validate is None or deploy is None:
        return None
    prior = validate["prior"]
    first = prior["skills_1"]
    horizons = sorted(prior, key=lambda k: int(k.removeprefix("skills_")))
    return {
        "tawm_error_by_skills": [prior[k]["tawm_error_mean"] for k in horizons],
        "tawm_nll_1": first["tawm_nll"],
        "tawm_within_1sigma_1": first["tawm_within_1sigma"],
        "tawm_error_1": first["tawm_error_mean"],
        **_deploy_numbers(deploy),
    }


def _pooled(runs: dict[str, dict[str, Any]]) -> dict[str, Any]:
    return pooled([r["success"] for r in runs.values()])


def _values(runs: dict[str, dict[str, Any]], key: str) -> list[float]:
    return [r[key] for r in runs.values() if r[key] is not None]


def _rounded(values: list[float]) -> list[float]:
    return [round(v, 3) for v in values]


def _em_vi_claims(tag: str, em: dict, vi: dict) -> list[dict[str, Any]]:
    """The paper's predictions (§2.1, appendix B, table 3) on one dataset, all seeds done."""
    claims = []
    for claim, key, higher_for in (
        ("VI's TAWM is overconfident: fewer real outcomes within 1 sigma than EM's",
         "tawm_within_1sigma_1", "em"),
        ("VI's TAWM gives real outcomes a higher NLL than EM's", "tawm_nll_1", "vi"),
        ("VI's plans are more optimistic than EM's (larger optimism gap)", "optimism_gap_m", "vi"),
    ):  # fmt: skip
        a, b = (_values(em, key), _values(vi, key))
        if not a or not b:
            continue
        verdict = separated(a, b) if higher_for == "em" else separated(b, a)
        claims.append({
            "claim": f"On the {tag} maze, {claim} (§2.1, table 3)",
            "verdict": verdict,
            "numbers": f"per seed EM {_rounded(a)}, VI {_rounded(b)}",
        })  # fmt: skip
    verdict, interval = versus(_pooled(em), _pooled(vi))
    claims.append({
        "claim": f"On the {tag} maze, OPOSM with EM reaches goals more often than with VI",
        "verdict": verdict,
        "numbers": f"EM {cell(_pooled(em))} vs VI {cell(_pooled(vi))} % (seeds pooled); "
        f"difference {points(interval)} points",
    })  # fmt: skip
    return claims


def em_vi(exp: dict[str, Any], repo: Path) -> tuple[dict[str, Any], list[dict[str, Any]], int]:
    """Per dataset tag and method, each finished seed's numbers; the claims on every dataset
    whose runs all finished; and how many runs finished."""
    cfg = exp.get("em_vi")
    if not cfg:
        return {}, [], 0
    table: dict[str, Any] = {}
    claims: list[dict[str, Any]] = []
    done = 0
    for dataset in cfg["datasets"]:
        runs = {}
        for method in METHODS:
            found = {}
            for seed in cfg["seeds"]:
                run = _run(repo / dataset["root"] / f"runs/{method}-seed{seed}")
                if run is not None:
                    found[str(seed)] = run
            runs[method] = found
            done += len(found)
        table[dataset["tag"]] = runs
        if all(len(runs[m]) == len(cfg["seeds"]) >= 3 for m in METHODS):
            claims += _em_vi_claims(dataset["tag"], runs["em"], runs["vi"])
    return table, claims, done


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
                "by_st_nll": _deploy_numbers(posterior),
                "by_st_nll_prior": _deploy_numbers(prior),
            }
        table[dataset["tag"]] = rows
        if len(rows) == len(cfg["seeds"]) >= 3:
            prior_pool = _pooled({k: r["by_st_nll_prior"] for k, r in rows.items()})
            post_pool = _pooled({k: r["by_st_nll"] for k, r in rows.items()})
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


def _gap(value: float | None) -> str:
    return "–" if value is None else f"{value:+.3f}"


def em_vi_tables(table: dict[str, Any]) -> list[str]:
    """Per run, then pooled per dataset and method."""
    rows = [
        "| data | method | seed | NLL, 1 skill | within 1 sigma | error (m) | success | gap (m) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    pooled = ["| data | method | seeds | success, pooled | mean gap (m) |", "|---|---|---|---|---|"]
    for tag, methods in table.items():
        for method, runs in methods.items():
            for seed, r in runs.items():
                rows.append(
                    f"| {tag} | {method} | {seed} | {r['tawm_nll_1']:.3f} | "
                    f"{pct(r['tawm_within_1sigma_1'])} | {r['tawm_error_1']:.3f} | "
                    f"{cell(r['success'])} | {_gap(r['optimism_gap_m'])} |"
                )
            if runs:
                gaps = _values(runs, "optimism_gap_m")
                mean_gap = sum(gaps) / len(gaps) if gaps else None
                pooled.append(
                    f"| {tag} | {method} | {len(runs)} | {cell(_pooled(runs))} | {_gap(mean_gap)} |"
                )
    if len(rows) == 2:
        return ["Not run yet."]
    return [*rows, "", *pooled]


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
            gap = _mean(_values(runs, "optimism_gap_m"))
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
