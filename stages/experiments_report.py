"""The paper's experiments page (`oposm report experiments`, the last stage of
experiments/dvc.yaml): the paper's experiments beside the paper's numbers, one verdict per claim.

Reads the deploy reports the experiments pipeline wrote (`<root>/runs/experiments/` per maze,
`<root>/runs/mass-<factor>/` per mass factor; the roots are in `experiments/params.yaml`) and
writes `results/experiments.md` (the report), `results/experiments.json` (the same numbers),
`results/metrics.json` (a few headline numbers: what `dvc metrics show` lists) and the CSVs
behind `dvc plots show experiments/dvc.yaml`. An experiment whose reports are missing is reported
as not run.

Verdicts follow the rules of `pipeline.reporting.common`: a difference between two agents holds
when its Newcombe interval excludes 0 in the claimed direction, does not hold when it excludes 0
the other way, and is inconclusive otherwise (`versus`; the mass sweep compares the success pooled
over the perturbed factors, `off_nominal`). A paper success rate is reproduced unless ours is
significantly below it: the interval of ours minus the paper's (its rate taken as
`pipeline.evaluation.published.EPISODES_MAZE2D` episodes; it ran 250-300 per maze) lies below 0
(`reproduces`).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

import yaml

from pipeline.errors import UserError
from pipeline.evaluation.published import (
    EPISODES_MAZE2D,
    FIGURE5,
    FIGURE5_FACTORS,
    PLAN_SECONDS,
    TABLE4,
)
from pipeline.io import atomic_path, write_json
from pipeline.reporting.common import (
    Report,
    cell,
    off_nominal,
    pct,
    points,
    rate,
    read,
    reproduces,
    stamp,
    stamp_text,
    versus,
)
from stages.results_em_vi import em_vi, em_vi_tables, selection, selection_tables
from stages.results_em_vi import plot_rows as em_vi_plot_rows

AGENTS = ("oposm", "llp", "gcbc", "expert")


def _task(t: dict[str, Any]) -> dict[str, Any]:
    out = {"success": rate(t["successes"], t["episodes"])}
    for limit, w in t.get("within_steps", {}).items():
        out[f"within_{limit}"] = rate(w["successes"], t["episodes"])
    return out


def _agent_numbers(report: Report) -> dict[str, Any]:
    out = {}
    for agent, r in report["by_agent"].items():
        out[agent] = {task: _task(r[task]) for task in report["tasks"]}
        per_env = r["planning"]["per_env_latency_s"]
        out[agent]["replan_s_p50"] = per_env["p50"]
        out[agent]["flops_per_replan"] = r.get("flops_per_replan")
    return out


def _maze_claims(maze: str, numbers: dict[str, Any]) -> list[dict[str, Any]]:
    claims = []
    rg = {a: numbers[a]["random_goal"]["success"] for a in numbers if "random_goal" in numbers[a]}
    published = TABLE4.get(maze, {})
    if "oposm" in rg and "oposm" in published:
        ours, (theirs, _) = rg["oposm"], published["oposm"]
        n = EPISODES_MAZE2D
        verdict, interval = reproduces(ours, theirs, n)
        claims.append(
            {
                "claim": f"OPOSM reaches random goals in maze2d-{maze} (table 4: {pct(theirs)} %)",
                "verdict": verdict,
                "numbers": f"ours {cell(ours)} % in 2000 steps; ours - paper's (as {n} "
                f"episodes) {points(interval)} points",
            }
        )
    if "oposm" in rg and "llp" in rg:
        verdict, interval = versus(rg["oposm"], rg["llp"])
        paper_llp = published.get("llp")
        said = f" (table 4: {pct(paper_llp[0])} %)" if paper_llp else ""
        claims.append(
            {
                "claim": f"OPOSM reaches random goals more often than LLP{said}, {maze}",
                "verdict": verdict,
                "numbers": f"OPOSM {cell(rg['oposm'])} vs LLP {cell(rg['llp'])} %; difference "
                f"{points(interval)} points",
            }
        )
    if "oposm" in numbers and "llp" in numbers:
        ours, theirs = numbers["oposm"]["replan_s_p50"], numbers["llp"]["replan_s_p50"]
        if ours and theirs:
            claimed = PLAN_SECONDS["llp"] / PLAN_SECONDS["oposm"]
            claims.append(
                {
                    "claim": f"OPOSM finds a plan faster than LLP (§4.2: {claimed:.0f}x), {maze}",
                    "verdict": "holds" if theirs > ours else "does not hold",
                    "numbers": f"per replan p50 OPOSM {ours * 1e3:.1f} ms, LLP "
                    f"{theirs * 1e3:.1f} ms (LLP/OPOSM {theirs / ours:.2f}x) at the paper "
                    "code's maze2d LLP settings",
                }
            )
    return claims


def _mass(report_of: dict[str, Report | None], factors: dict[str, float]) -> dict[str, Any]:
    """Success per agent and factor (tasks pooled), and each agent's success under every factor
    but the nominal one, pooled."""
    table: dict[str, dict[str, Any]] = {}
    for key, factor in factors.items():
        report = report_of[key]
        if report is None:
            continue
        for agent, r in report["by_agent"].items():
            wins = sum(r[t]["successes"] for t in report["tasks"])
            n = sum(r[t]["episodes"] for t in report["tasks"])
            table.setdefault(agent, {})[str(factor)] = rate(wins, n)
    perturbed = {a: p for a, by_factor in table.items() if (p := off_nominal(by_factor))}
    return {"success": table, "perturbed_pooled": perturbed}


def _mass_claims(mass: dict[str, Any]) -> list[dict[str, Any]]:
    pooled = mass["perturbed_pooled"]
    claims = []
    for other in ("expert", "gcbc"):
        if "oposm" in pooled and other in pooled:
            verdict, interval = versus(pooled["oposm"], pooled[other])
            claims.append(
                {
                    "claim": f"OPOSM stays more successful than {other} when the mass "
                    "changes (fig. 5)",
                    "verdict": verdict,
                    "numbers": f"pooled over factors != 1: OPOSM {cell(pooled['oposm'])} vs "
                    f"{other} {cell(pooled[other])} %; difference {points(interval)} "
                    "points",
                }
            )
    return claims


def collect(experiments: Path, repo: Path) -> dict[str, Any]:
    """The numbers and verdicts of every experiment whose reports exist (`deploy.roots` and
    `mass.root` of `experiments` are relative to `repo`)."""
    try:
        exp = yaml.safe_load(experiments.read_text())
    except FileNotFoundError as exc:
        raise UserError(f"{experiments}: not found; run from the repository root") from exc
    results: dict[str, Any] = {"mazes": {}, "claims": [], "not_run": []}
    for maze, root in exp["deploy"]["roots"].items():
        report = read(repo / root / "runs/experiments/reports/deploy/report.json")
        if report is None:
            results["not_run"].append(f"maze sizes: {maze}")
            continue
        numbers = _agent_numbers(report)
        results["mazes"][maze] = {
            "env_id": report["env_id"],
            "max_steps": report["max_steps"],
            "shorter_limits": report["shorter_limits"],
            "episodes_per_task": report["episodes_per_task"],
            "deploy_wall_s": report["wall_s"],
            "agents": numbers,
        }
        results["claims"] += _maze_claims(maze, numbers)
    mass_cfg = exp["mass"]
    runs = repo / mass_cfg["root"] / "runs"
    reports = {k: read(runs / f"mass-{k}/reports/deploy/report.json") for k in mass_cfg["factors"]}
    results["not_run"] += [f"mass: {k}" for k, r in reports.items() if r is None]
    results["mass"] = {"maze": mass_cfg["maze"], **_mass(reports, mass_cfg["factors"])}
    results["claims"] += _mass_claims(results["mass"])
    results["em_vi"], em_vi_claims, runs_done = em_vi(exp, repo)
    results["claims"] += em_vi_claims
    cfg = exp.get("em_vi") or {}
    results["em_vi_e_kl"] = cfg.get("e_kl")
    runs_planned = len(cfg.get("datasets", [])) * 2 * len(cfg.get("seeds", []))
    if runs_done < runs_planned:
        results["not_run"].append(
            f"EM vs naive VI (table 3): {runs_done} of its {runs_planned} runs have finished"
        )
    results["selection"], selection_claims = selection(exp, repo)
    results["claims"] += selection_claims
    selected = sum(len(seeds) for seeds in results["selection"].values())
    if selected < runs_planned // 2:
        results["not_run"].append(
            f"model selection: {selected} of its {runs_planned // 2} deploys have finished"
        )
    results["stamp"] = stamp(repo)
    return results


def _stamp(results: dict[str, Any]) -> dict[str, Any]:
    """The report's stamp (results written before the stamp: their machine and commit)."""
    if "stamp" in results:
        return results["stamp"]
    return {"machine": results.get("assembled_on"), "commit": results.get("code")}


def _maze_table(results: dict[str, Any]) -> list[str]:
    lines = [
        "| maze | task | agent | success, 2000 steps | within D4RL's limit | paper (table 4) |",
        "|---|---|---|---|---|---|",
    ]
    for maze, m in results["mazes"].items():
        limit = (m["shorter_limits"] or [None])[0]
        for task in ("random_goal", "corners"):
            for agent in AGENTS:
                t = m["agents"].get(agent, {}).get(task)
                if t is None:
                    continue
                published = TABLE4.get(maze, {}).get(agent) if task == "random_goal" else None
                said = f"{pct(published[0])} ± {pct(published[1])}" if published else "–"
                within = cell(t.get(f"within_{limit}")) + f" ({limit})" if limit else "–"
                lines.append(
                    f"| {maze} | {task} | {agent} | {cell(t['success'])} | {within} | {said} |"
                )
    return lines


def _mass_table(results: dict[str, Any]) -> list[str]:
    table = results["mass"]["success"]
    factors = sorted({f for by in table.values() for f in by}, key=float)
    if not factors:
        return ["Not run yet."]
    lines = [
        "| agent | " + " | ".join(f"x{float(f):g}" for f in factors) + " |",
        "|---|" + "---|" * len(factors),
    ]
    for agent in AGENTS:
        if agent in table:
            cells = [cell(table[agent].get(f)) for f in factors]
            lines.append(f"| {agent} (ours) | " + " | ".join(cells) + " |")
    for agent, series in FIGURE5.items():
        by = dict(zip(FIGURE5_FACTORS, series, strict=True))
        cells = [pct(by[float(f)]) if float(f) in by else "–" for f in factors]
        lines.append(f"| {agent} (paper, antmaze-large) | " + " | ".join(cells) + " |")
    return lines


def _em_vi_kl(results: dict[str, Any]) -> str:
    """Which KL estimator EM's E-step used beside VI's closed form (`em_vi.e_kl`)."""
    e_kl = results.get("em_vi_e_kl")
    if e_kl == "closed_form":
        return ("EM's E-step with VI's closed-form KL (`em_vi.e_kl`), so that the two differ in "
                "their updates only")  # fmt: skip
    when = "`em_vi.e_kl`" if e_kl else "runs made before `em_vi.e_kl`"
    return (f"EM's E-step with the {e_kl or 'sampled'} KL, VI's in closed form ({when}: the "
            "estimators differ too)")  # fmt: skip


def markdown(results: dict[str, Any]) -> str:
    """The report: verdicts first, then each experiment beside the paper."""
    out = [
        "# The paper's experiments: our numbers beside the paper's",
        "",
        "Made by `oposm results` (the last stage of `uv run dvc repro experiments/dvc.yaml`) "
        f"from the deploy reports of the experiments that have run; {stamp_text(_stamp(results))} "
        "(the stages' own code versions are in experiments/dvc.lock). "
        "Success rates in %, with 95 % Wilson intervals in brackets; differences with Newcombe "
        "intervals. Verdicts: a claim holds when the interval excludes the opposite.",
        "",
        "## Verdicts",
        "",
        "| claim | verdict | numbers |",
        "|---|---|---|",
        *(f"| {c['claim']} | **{c['verdict']}** | {c['numbers']} |" for c in results["claims"]),
        "",
        "## 1. Maze sizes (paper table 4, maze2d rows)",
        "",
        "The same episodes for every agent (start cells, goals and seeds); the paper code's "
        "protocol: up to 2000 steps, success = came within 0.5 m of the goal. D4RL's step "
        "limit (umaze 300, medium 600, large 800) in the next column. `corners` is D4RL's "
        "opposite-corner task.",
        "",
        *_maze_table(results),
        "",
        "## 2. EM vs naive VI (paper table 3)",
        "",
        "The paper's table 3 compares the two on antmaze-medium and -large (success) and "
        "kitchen (reward); here on the main job's maze and the same maze with random pushes "
        "(`em_vi.pushes` in experiments/params.yaml), EM and naive VI with each seed, "
        f"{_em_vi_kl(results)}; per seed: the TAWM after one prior skill (NLL of the real "
        "outcome, fraction within 1 sigma: 68.3 % when calibrated, mean position error), "
        "OPOSM's deploy success and its optimism gap (real minus predicted distance to the goal "
        "where each plan's first skill ends).",
        "",
        *em_vi_tables(results["em_vi"]),
        "",
        f"## 3. Robustness to mass (paper figure 5), {results['mass']['maze']} maze",
        "",
        "Success (random goals and corners pooled) with every body's mass and inertia scaled in "
        "the simulator, the models as trained. The paper's rows are antmaze-large with a scaled "
        "geom density, for the shape of the curves only. Our expert is the scripted waypoint + "
        "PD controller that made the data: a feedback controller that knows the maze, unlike "
        "the paper's learned ant policy, so a heavier point only slows it down.",
        "",
        *_mass_table(results),
        "",
        "## 4. Model selection",
        "",
        "Each EM run of experiment 2 keeps two best checkpoints: by the validation s_T NLL "
        "under the posterior skill (`train.select: st_nll`, pinned for these runs, deployed "
        "above) and by the s_T NLL with the skill drawn from the prior, 64 draws "
        "(`st_nll_prior`: what a planner drawing skills from the prior may expect). OPOSM "
        "deployed with each on the same episodes:",
        "",
        *selection_tables(results["selection"]),
        "",
    ]
    if results["not_run"]:
        out += ["## Not run", "", *(f"- {x}" for x in results["not_run"]), ""]
    return "\n".join(out)


def _csv(rows: list[dict[str, Any]]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buffer.getvalue()


def plot_rows(results: dict[str, Any]) -> dict[str, list[dict[str, Any]]]:
    """The CSVs of experiments/dvc.yaml's plots: success vs mass factor, success per maze, and
    experiment 2's error vs horizon and optimism gap."""
    mass = results["mass"]["success"]
    factors = sorted({f for by in mass.values() for f in by}, key=float)
    mass_rows = [
        {"mass_factor": float(f), **{a: mass[a][f]["rate"] for a in AGENTS if f in mass.get(a, {})}}
        for f in factors
    ]
    maze_rows = [
        {"maze": maze, **{a: m["agents"][a]["random_goal"]["success"]["rate"] for a in m["agents"]}}
        for maze, m in results["mazes"].items()
    ]
    return {"mass.csv": mass_rows, "mazes.csv": maze_rows, **em_vi_plot_rows(results["em_vi"])}


def headline(results: dict[str, Any]) -> dict[str, Any]:
    """The few numbers `dvc metrics show` lists: verdict counts, OPOSM's random-goal success per
    maze that ran, and the mass sweep's pooled success off the nominal mass per agent."""
    verdicts = [c["verdict"] for c in results["claims"]]
    out: dict[str, Any] = {"claims": len(verdicts), "holding": verdicts.count("holds")}
    for maze, m in results["mazes"].items():
        oposm = m["agents"].get("oposm", {}).get("random_goal")
        if oposm is not None:
            out[f"{maze}_oposm_random_goal"] = round(oposm["success"]["rate"], 4)
    for agent, r in results["mass"]["perturbed_pooled"].items():
        out[f"mass_{agent}"] = round(r["rate"], 4)
    return out


def _write_text(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def run(experiments: Path, repo: Path, out: Path) -> dict[str, Any]:
    """Collect, judge and write `out/` (experiments.md, experiments.json, the plots' CSVs)."""
    results = collect(experiments, repo)
    out.mkdir(parents=True, exist_ok=True)
    _write_text(out / "experiments.md", markdown(results))
    write_json(out / "experiments.json", results)
    write_json(out / "metrics.json", headline(results))
    for name, rows in plot_rows(results).items():
        if rows:
            _write_text(out / name, _csv(rows))
    return results
