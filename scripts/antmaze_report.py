"""results/antmaze.md + results/antmaze.json: OPOSM on OGBench's ant mazes.

Collects what the per-maze runs wrote (one data root per maze, e.g. `--data data/ant/medium`):
the data (ingest, segment), training, validation (TAWM vs single-step open loop) and deployment on
OGBench's five evaluation tasks, with the shipped expert's own check (`experts/ant/actor.json`)
and the published numbers beside ours. Reruns of the commands it lists reproduce every number.

    uv run python scripts/antmaze_report.py --maze medium=data/ant/medium \
        --commands results/antmaze-commands.json [--maze large=...]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

from pipeline.errors import UserError
from pipeline.evaluation import paper
from pipeline.io import atomic_path, write_json
from stages.results_common import code_version, read

ROOT = Path(__file__).resolve().parents[1]

# The published numbers, from their one place (pipeline/evaluation/paper.py), as printed here:
# OGBench's navigate table (percent mean, std over its seeds), the paper's tables 1 and 4.
PUBLISHED = {
    maze: {
        method: (round(100 * mean), round(100 * std))
        for method, (mean, std) in paper.OGBENCH[f"antmaze-{maze}-navigate"].items()
    }
    for maze in ("medium", "large")
}
PAPER = {
    maze: {
        f"table {n} ({what})": f"{100 * m:.4g} +- {100 * sd:.3g}"
        for n, what, table in ((1, "fixed goal", paper.TABLE1), (4, "random goals", paper.TABLE4))
        for m, sd in [table[f"antmaze-{maze}-diverse"]["oposm"]]
    }
    for maze in ("medium", "large")
}


MASS_RUN = "mass"  # runs named mass<factor> (`deploy.mass_scale`): the figure-5 sweep
# The paper's figure 5 (antmaze-large, geom density x0.2 ... x5), success in percent.
FIG5_FACTORS = list(paper.FIGURE5_FACTORS)
PAPER_FIG5 = {k: [round(100 * v, 1) for v in paper.FIGURE5[k]] for k in ("oposm", "expert")}


def _pct(rate: float | None, lo: float | None = None, hi: float | None = None) -> str:
    if rate is None:
        return "–"
    text = f"{100 * rate:.0f}"
    return text if lo is None else f"{text} ({100 * lo:.0f}-{100 * hi:.0f})"


def collect(maze: str, root: Path) -> dict:
    reports = root / "reports"
    out: dict = {"data_root": str(root)}
    for stage in ("ingest", "segment", "dynamics", "validate"):
        out[stage] = read(reports / stage / "report.json")
    out["train"] = read(reports / "train" / "metrics.json")
    runs = sorted((root / "runs").glob("*/reports/deploy/report.json"))
    mass = [p for p in runs if p.parents[2].name.startswith(MASS_RUN)]
    others = [p for p in runs if p not in mass]
    out["deploy"] = _merged_deploys([reports / "deploy" / "report.json"] + others)
    out["mass_sweep"] = _mass_sweep(mass)
    out["random_goal"] = _random_goal_runs(others)
    return out


def _random_goal_runs(paths: list[Path]) -> dict:
    """Runs on training-data goals (`deploy.tasks: [random_goal]`, the development metric),
    by run name: each agent's success with its interval, episodes and final distance."""
    runs: dict = {}
    for path in paths:
        r = read(path)
        if not r or r.get("tasks") != ["random_goal"]:
            continue
        runs[path.parents[2].name] = {
            agent: {
                k: by_task["random_goal"].get(k)
                for k in (
                    "episodes",
                    "success_rate",
                    "success_ci95_low",
                    "success_ci95_high",
                    "final_distance_mean",
                    "fallen",
                )
            }
            for agent, by_task in r["by_agent"].items()
        }
    return runs


def _mass_sweep(paths: list[Path]) -> dict | None:
    """Overall success per agent and mass factor, from runs named `mass<factor>`."""
    sweep: dict = {}
    for path in paths:
        r = read(path)
        if not r:
            continue
        for agent, by_task in r["by_agent"].items():
            o = by_task["ogbench"]
            sweep.setdefault(agent, {})[str(r["mass_scale"])] = {
                "success_rate": o["success_rate"],
                "success_ci95_low": o["success_ci95_low"],
                "success_ci95_high": o["success_ci95_high"],
                "episodes": r["episodes_per_task"] * (len(r["tasks"]) - 1),
            }
    for agent in sweep:
        sweep[agent] = dict(sorted(sweep[agent].items(), key=lambda kv: float(kv[0])))
    return sweep or None


def _mass_rows(sweep: dict) -> list[str]:
    agents = list(sweep)
    factors = sorted({f for a in agents for f in sweep[a]}, key=float)
    head = " | ".join(agents) + " | paper: OPOSM (large) | paper: expert (large)"
    rows = [f"| mass factor | {head} |", "|---" * (len(agents) + 3) + "|"]
    for f in factors:
        cells = []
        for a in agents:
            v = sweep[a].get(f)
            cells.append(
                _pct(v["success_rate"], v["success_ci95_low"], v["success_ci95_high"]) if v else "–"
            )
        i = FIG5_FACTORS.index(float(f)) if float(f) in FIG5_FACTORS else None
        cells += [f"{PAPER_FIG5[k][i]:g}" if i is not None else "–" for k in ("oposm", "expert")]
        rows.append(f"| x{f} | " + " | ".join(cells) + " |")
    kept = {a: k for a in agents if (k := kept_share(sweep[a])) is not None}
    if kept:
        rows += [
            "",
            "Mean success over the perturbed factors as a share of the success at x1: "
            + ", ".join(f"{a} {100 * k:.0f} %" for a, k in kept.items())
            + ".",
        ]
    if "oposm" in kept and "expert" in kept:
        gap = kept["oposm"] - kept["expert"]
        word = "holds" if gap > 0.1 else "does not hold" if gap < -0.1 else "inconclusive"
        rows += [
            "",
            "Verdict (paper figure 5: OPOSM keeps more of its success under mass changes than "
            f"the expert policy): **{word}** (shares {100 * kept['oposm']:.0f} % vs "
            f"{100 * kept['expert']:.0f} %; within 10 points: inconclusive).",
        ]
    return rows


def kept_share(by_factor: dict) -> float | None:
    """Mean success over the factors other than x1, as a share of the success at x1."""
    base = by_factor.get("1.0", {}).get("success_rate")
    others = [v["success_rate"] for f, v in by_factor.items() if float(f) != 1.0]
    return sum(others) / len(others) / base if base and others else None


def _merged_deploys(paths: list[Path]) -> dict | None:
    """The agents of every deploy report of a maze (ad-hoc `--run`s included), each agent with
    its own episodes per task (the same tasks and seeds: a smaller run deploys the first ones);
    an agent in several reports gets one row per report, the later ones named after their run."""
    found = [(p, r) for p in paths if (r := read(p)) and "ogbench" in r.get("tasks", [])]
    if not found:  # runs on other tasks (random_goal: choices on training-data goals) left out
        return None
    merged = {k: v for k, v in found[0][1].items() if k != "by_agent"}
    merged["by_agent"], merged["episodes_by_agent"] = {}, {}
    for path, r in found:
        for agent, by_task in r["by_agent"].items():
            # an agent met again (another setting, another run) is named after its run
            name = (
                agent
                if agent not in merged["by_agent"]
                else f"{agent} (run {path.parents[2].name})"
            )
            merged["by_agent"][name] = by_task
            merged["episodes_by_agent"][name] = r["episodes_per_task"]
    return merged


def _deploy_rows(deploy: dict) -> list[str]:
    tasks = [t for t in deploy["tasks"] if t != "ogbench"]
    names = " | ".join(t.replace("ogbench-", "") for t in tasks)
    head = f"| agent | per task | {names} | overall | fell |"
    rows = [head, "|---" * (len(tasks) + 4) + "|"]
    for agent, by_task in deploy["by_agent"].items():
        cells = [
            _pct(
                by_task[t]["success_rate"],
                by_task[t]["success_ci95_low"],
                by_task[t]["success_ci95_high"],
            )
            for t in [*tasks, "ogbench"]
        ]
        cells[-1] = f"**{cells[-1]}**"
        fell = by_task["ogbench"].get("fallen")  # episodes the ant fell in (newer deploys)
        cells.append("–" if fell is None else str(fell))
        n = deploy.get("episodes_by_agent", {}).get(agent, deploy["episodes_per_task"])
        rows.append(f"| {agent} | {n} | " + " | ".join(cells) + " |")
    return rows


def _expert_row(expert: dict, env_id: str) -> str | None:
    maze = expert.get("quality", {}).get("mazes", {}).get(env_id)
    if not maze:
        return None
    cells = [
        _pct(t["success_rate"], t["success_ci95_low"], t["success_ci95_high"])
        for t in maze["tasks"]
    ]
    o = maze["overall"]
    overall = _pct(o["success_rate"], o["success_ci95_low"], o["success_ci95_high"])
    n = maze["tasks"][0]["episodes"]
    return (
        f"| expert (noise-free, `oposm expert check`) | {n} | "
        + " | ".join(cells)
        + f" | **{overall}** | – |"
    )


def render(results: dict) -> str:
    expert = results["expert"]
    lines = [
        "# OGBench ant mazes: OPOSM beside OGBench's published table",
        "",
        "Produced by `uv run python scripts/antmaze_report.py` from the runs listed "
        "per maze (their commands below); every setting is in `antmaze.json`.",
        "",
        f"Machine: {results['machine']}. Commit: {results.get('commit') or 'unknown'}.",
        "",
        "## Protocol",
        "",
        "- Environment: OGBench's `antmaze-{medium,large}-v0` (ogbench's locomaze: the D4RL ant, "
        "gear 30, 0.1 s per step), 29-dim state (qpos + qvel), 8 torques.",
        "- Tasks: its five evaluation tasks per maze (start and goal cells with its noise), "
        "at most 1000 steps, success within 0.5 of the goal. The planner gets the goal "
        "as `[x, y]`; OGBench's agents get a full goal observation (29 numbers: a standing "
        "ant at the goal).",
        "- Data: OGBench's `navigate` recipe run here with our expert in the place of OGBench's "
        "(BFS oracle direction -> our direction-commanded SAC actor -> + N(0, 0.2), clipped; a new "
        "goal on each reach; 1001-step episodes); episodes per maze below (OGBench's files: 1000).",
        f"- Expert: `experts/ant/actor.safetensors`, {expert.get('steps')} SAC steps "
        f"({expert.get('sac_phases')}).",
        "",
    ]
    for maze, r in results["mazes"].items():
        lines += [f"## antmaze-{maze}-navigate", ""]
        ingest, train, validate, deploy = r["ingest"], r["train"], r["validate"], r["deploy"]
        if ingest:
            lines.append(
                f"- Data: {ingest['episodes']:.0f} episodes, {ingest['steps']:.0f} steps; ant "
                f"fallen or upside down in {ingest.get('fallen_steps', 0):.0f} steps "
                f"({ingest.get('fallen_episodes', 0):.0f} "
                f"episodes); {ingest.get('goals_per_1000_steps', float('nan')):.1f} goals reached "
                "per 1000 steps."
            )
        lines += [f"- {note}" for note in r.get("notes", [])]
        if train:
            val = train["val"]
            lines.append(
                f"- Training (EM): {train['steps']} steps ({train['steps_per_s']:.2f} steps/s, "
                f"{train['wall_s'] / 60:.0f} min in all on {train.get('device')}); "
                f"published checkpoint by `{train['select']}` at step {train['best_step']}; "
                f"validation s_T NLL {train['val']['st_nll']:.2f} (posterior skill), "
                f"{train['val']['st_nll_prior']:.2f} (prior skills), KL(q || prior) "
                f"{val.get('kl', float('nan')):.1f} nats at the last evaluation."
            )
        if validate:
            prior = validate["prior"]
            parts = [
                f"{k.split('_')[1]} skill(s) ({v['steps']} steps): TAWM "
                f"{v['tawm_error_mean']:.2f} m, single-step {v['single_step_error_mean']:.3g} m, "
                f"no model {v['no_model_error_mean']:.2f} m; within 1 sigma "
                f"{100 * v['tawm_within_1sigma']:.0f} %"
                for k, v in prior.items()
            ]
            lines += [
                f"- Open loop, prior skills from {validate['starts']} held-out starts (mean x-y "
                "error of the predicted end; paper figure 4 is antmaze-large):",
                *[f"  - {p}" for p in parts],
            ]
            replay = [
                f"{k.split('_')[1]} skill(s) ({v['steps']} steps): executed "
                f"{v['replay_error_mean']:.2f} m, TAWM {v['tawm_recorded_error_mean']:.2f} m, "
                f"no model {v['no_model_recorded_error_mean']:.2f} m"
                for k, v in validate.get("posterior", {}).items()
                if "replay_error_mean" in v
            ]
            if replay:
                lines += [
                    "- Skill fidelity: the posterior's skills of held-out recorded windows, "
                    "executed by the policy in MuJoCo from the recorded start (mean x-y distance "
                    "to the recorded end; a policy that replays its skills lands well below "
                    "no model):",
                    *[f"  - {p}" for p in replay],
                ]
        for run, agents in r.get("random_goal", {}).items():
            for agent, v in agents.items():
                rate = _pct(v["success_rate"], v["success_ci95_low"], v["success_ci95_high"])
                lines.append(
                    f"- Goals from the training data (`random_goal`, run `{run}`, the "
                    f"development metric): {agent} {rate} % "
                    f"of {v['episodes']} episodes; mean final distance "
                    + (
                        "–"
                        if v["final_distance_mean"] is None
                        else f"{v['final_distance_mean']:.2f}"
                    )
                    + f" m; fell in {v['fallen'] if v.get('fallen') is not None else '–'}."
                )
        lines.append("")
        if deploy:
            lines += [
                "Success (%, 95 % Wilson interval), episodes per task as listed, at most "
                f"{deploy['max_steps']} steps:",
                "",
                *_deploy_rows(deploy),
            ]
        else:
            lines += ["Not deployed yet.", ""]
            row = _expert_row(expert, f"antmaze-{maze}-v0")
            if row:
                lines += [
                    "| agent | per task | task1 | task2 | task3 | task4 | task5 | overall | fell |",
                    "|---|---|---|---|---|---|---|---|---|",
                ]
        row = _expert_row(expert, f"antmaze-{maze}-v0")
        if row:
            lines.append(row)
        if r.get("mass_sweep"):
            lines += [
                "",
                "Robustness to the ant's mass (paper figure 5: every body's mass and inertia times "
                "the factor in the simulator, the models unchanged), success % (95 % Wilson "
                "interval) over OGBench's five tasks, beside the paper's (antmaze-large):",
                "",
                *_mass_rows(r["mass_sweep"]),
            ]
        lines += [
            "",
            "Published (OGBench's paper, navigate, 8 seeds): "
            + ", ".join(f"{k} {m} +- {s}" for k, (m, s) in PUBLISHED[maze].items())
            + ". The paper (D4RL antmaze-"
            + maze
            + "-diverse, its own goals, not this protocol): "
            + ", ".join(f"{k} {v}" for k, v in PAPER[maze].items())
            + ".",
            "",
        ]
        verdict = results["verdicts"].get(maze)
        if verdict:
            lines += [f"Verdict: {verdict}", ""]
        if r.get("commands"):
            lines += ["Commands:", "", "```bash", *r["commands"], "```", ""]
    return "\n".join(lines).rstrip() + "\n"


def verdict(maze: str, deploy: dict | None) -> str | None:
    """OPOSM vs the best published method: does its interval lie above, below, or overlap?"""
    if not deploy or "oposm" not in deploy["by_agent"]:
        return None
    o = deploy["by_agent"]["oposm"]["ogbench"]
    best, (mean, std) = max(PUBLISHED[maze].items(), key=lambda kv: kv[1][0])
    lo, hi = 100 * o["success_ci95_low"], 100 * o["success_ci95_high"]
    if lo > mean + std:
        word = "holds"
    elif hi < mean - std:
        word = "does not hold"
    else:
        word = "inconclusive"
    return (
        f"OPOSM beats every published method on antmaze-{maze}-navigate: **{word}** "
        f"(OPOSM {100 * o['success_rate']:.0f} % [{lo:.0f}, {hi:.0f}] vs {best} {mean} +- {std})."
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--maze", action="append", default=[], help="medium=DATA_ROOT (repeat)")
    parser.add_argument(
        "--commands",
        type=Path,
        help="JSON: maze -> the commands run (a list), or {commands: [...], notes: [...]}",
    )
    parser.add_argument(
        "--machine", help="where the runs ran (default: this machine, or with --keep the kept one)"
    )
    parser.add_argument("--out", type=Path, default=ROOT / "results")
    parser.add_argument(
        "--keep",
        action="store_true",
        help="keep the mazes of the existing OUT/antmaze.json that no --maze names (their data "
        "roots may be gone) and update only those given",
    )
    args = parser.parse_args()
    actor = read(ROOT / "experts" / "ant" / "actor.json") or {}
    info = actor.get("info", {})
    expert = {
        "steps": info.get("steps"),
        "sac_phases": ", then ".join(
            f"from step {p['from_step']}: action noise {p['action_noise']}"
            + (", episode ends on a flip" if p["terminate_upside_down"] else "")
            for p in info.get("sac", {}).get("phases", [])
        )
        or "OGBench's recipe",
        "quality": info.get("quality", {}),
    }
    commands = read(args.commands) if args.commands else {}
    previous = read(args.out / "antmaze.json") if args.keep else None
    mazes = dict((previous or {}).get("mazes", {}))
    for item in args.maze:
        maze, _, root = item.partition("=")
        run = (commands or {}).get(maze, [])  # a list of commands, or {commands, notes}
        run = run if isinstance(run, dict) else {"commands": run}
        mazes[maze] = collect(maze, Path(root)) | {
            "commands": run.get("commands", []),
            "notes": run.get("notes", []),
        }
    results = {
        "what": "OPOSM on OGBench's ant mazes, beside OGBench's published table",
        "machine": args.machine
        or (previous or {}).get("machine")
        or f"{platform.machine()} CPU, {os.cpu_count()} cores",
        "expert": expert,
        "mazes": mazes,
        "published_ogbench": PUBLISHED,
        "paper": PAPER,
        "verdicts": {m: v for m, r in mazes.items() if (v := verdict(m, r["deploy"]))},
        "commit": code_version(ROOT),
    }
    write_json(args.out / "antmaze.json", results)
    with atomic_path(args.out / "antmaze.md") as tmp:
        tmp.write_text(render(results))
    print(f"wrote {args.out / 'antmaze.md'} and antmaze.json")


if __name__ == "__main__":
    try:
        main()
    except UserError as exc:  # a corrupt report: one line naming it, no traceback
        sys.exit(f"error: {exc}")
