"""EM against naive VI (the paper's §2.1, appendix B, table 3), run by run: what one run's validate
and deploy reports say, the paper's predictions judged on all seeds of both methods, and the
tables. Used by the paper's experiments on the point maze (`stages/results_em_vi.py`) and by the
ant mazes' table 3 (`pipeline.reporting.antmaze`).

A run is a folder with `reports/validate/report.json` (the TAWM against real open-loop outcomes
of prior skills) and `reports/deploy/report.json` (OPOSM's success and optimism gap). Per-seed
values are compared with `separated` (all seeds of one method beyond all of the other's); success
rates are pooled over seeds and compared with `versus` (Newcombe interval).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.reporting.common import cell, pct, points, pooled, rate, read, separated, versus

METHODS = ("em", "vi")
MIN_SEEDS = 3  # per method, before a claim is judged
OGBENCH_POOLED = "ogbench"  # a deploy's row of OGBench's five tasks together (`deploy.tasks`)


def deploy_numbers(deploy: dict[str, Any]) -> dict[str, Any]:
    """OPOSM's success over every task of a deploy report, and its mean optimism gap (m)."""
    oposm = deploy["by_agent"]["oposm"]
    # OGBench's task set comes with its five tasks pooled: count each episode once
    tasks = [OGBENCH_POOLED] if OGBENCH_POOLED in deploy["tasks"] else deploy["tasks"]
    wins = sum(oposm[t]["successes"] for t in tasks)
    n = sum(oposm[t]["episodes"] for t in tasks)
    gaps = [g["distance_gap_m"]["mean"] for g in (oposm.get("optimism_gap") or {}).values()]
    gaps = [g for g in gaps if g is not None]
    return {"success": rate(wins, n), "optimism_gap_m": sum(gaps) / len(gaps) if gaps else None}


def run_numbers(root: Path) -> dict[str, Any] | None:
    """One run's numbers, or None until both its validate and deploy reports exist."""
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
        **deploy_numbers(deploy),
    }


def pooled_success(runs: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The success of every seed's episodes together."""
    return pooled([r["success"] for r in runs.values()])


def values(runs: dict[str, dict[str, Any]], key: str) -> list[float]:
    return [r[key] for r in runs.values() if r[key] is not None]


def _rounded(xs: list[float]) -> list[float]:
    return [round(x, 3) for x in xs]


def claims(tag: str, em: dict[str, Any], vi: dict[str, Any]) -> list[dict[str, Any]]:
    """The paper's predictions on one dataset (`tag` names it in the claim), its seeds all done:
    each a `claim`, its `verdict` and the `numbers` behind it."""
    out = []
    for claim, key, higher_for in (
        ("VI's TAWM is overconfident: fewer real outcomes within 1 sigma than EM's",
         "tawm_within_1sigma_1", "em"),
        ("VI's TAWM gives real outcomes a higher NLL than EM's", "tawm_nll_1", "vi"),
        ("VI's plans are more optimistic than EM's (larger optimism gap)", "optimism_gap_m", "vi"),
    ):  # fmt: skip
        a, b = (values(em, key), values(vi, key))
        if not a or not b:
            continue
        verdict = separated(a, b) if higher_for == "em" else separated(b, a)
        out.append({
            "claim": f"On the {tag} maze, {claim} (§2.1, table 3)",
            "verdict": verdict,
            "numbers": f"per seed EM {_rounded(a)}, VI {_rounded(b)}",
        })  # fmt: skip
    verdict, interval = versus(pooled_success(em), pooled_success(vi))
    out.append({
        "claim": f"On the {tag} maze, OPOSM with EM reaches goals more often than with VI",
        "verdict": verdict,
        "numbers": f"EM {cell(pooled_success(em))} vs VI {cell(pooled_success(vi))} % (seeds "
        f"pooled); difference {points(interval)} points",
    })  # fmt: skip
    return out


def _gap(value: float | None) -> str:
    return "–" if value is None else f"{value:+.3f}"


def tables(table: dict[str, Any]) -> list[str]:
    """Markdown: per run (dataset tag -> method -> seed -> `run_numbers`), then pooled per dataset
    and method."""
    rows = [
        "| data | method | seed | NLL, 1 skill | within 1 sigma | error (m) | success | gap (m) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    pooled_rows = [
        "| data | method | seeds | success, pooled | mean gap (m) |",
        "|---|---|---|---|---|",
    ]
    for tag, methods in table.items():
        for method, runs in methods.items():
            for seed, r in runs.items():
                rows.append(
                    f"| {tag} | {method} | {seed} | {r['tawm_nll_1']:.3f} | "
                    f"{pct(r['tawm_within_1sigma_1'])} | {r['tawm_error_1']:.3f} | "
                    f"{cell(r['success'])} | {_gap(r['optimism_gap_m'])} |"
                )
            if runs:
                gaps = values(runs, "optimism_gap_m")
                mean_gap = sum(gaps) / len(gaps) if gaps else None
                pooled_rows.append(
                    f"| {tag} | {method} | {len(runs)} | {cell(pooled_success(runs))} | "
                    f"{_gap(mean_gap)} |"
                )
    if len(rows) == 2:
        return ["Not run yet."]
    return [*rows, "", *pooled_rows]
