"""results/antmaze.md + .json: OPOSM on OGBench's ant mazes, beside OGBench's published table and
the paper's tables 1 and 4 (and figure 5 when a mass sweep ran), on `pipeline.reporting.common`'s
format, verdict rules and stamp, with the published numbers of `pipeline.evaluation.published`
(the OPOSM paper's and OGBench's).

One data root per maze (`experiments/antmaze/dvc.yaml`: `data/experiments/antmaze/<maze>/`): the
data (ingest, segment), training, validation (the ladder's skill fidelity and prior-skill open
loop), and deploy runs under `runs/<run>/`: one per agent on OGBench's five tasks, one on goals
from the training data (`random_goal`, the development metric), and runs named `mass<...>`
(figure 5: `deploy.mass_scale`) and `table3-<method>-seed<seed>` (table 3: EM against naive
VI, each run trained, validated and deployed on its own).

Two steps, so that a maze's report outlives its data root (DVC's cache is local: a maze run
on another day or machine keeps its report in git): stage `maze@<maze>` writes the maze's report,
`results/antmaze/<maze>.json` (`maze_report`), from its data root; stage `figure5` writes the mass
sweep's, `results/antmaze/<maze>-figure5.json` (`figure5_report`), from the same root's mass runs
alone (its own stage: a maze without a sweep has no such runs to depend on); stage `table3` writes
`results/antmaze/<maze>-table3.json` (`table3_report`) from its table3-* runs alike; stage
`report` writes the page, `results/antmaze.md` and `.json` (`page`), from every maze's, sweep's
and table 3's report.

Two protocols from one run. The deploys run the paper code's episodes (`deploy.max_steps: 2000`,
success when the ant comes within 0.5 of the goal); OGBench's protocol (1000 steps, 0.5) is the
same episodes' success within their first 1000 steps (an episode runs the same up to a limit
whatever its own limit: `pipeline.evaluation.stats.success_within`). A run of 1000 steps gives
OGBench's protocol only.

Verdicts, each with its rule of `pipeline.reporting.common`:

- "OPOSM is above every published method" (OGBench's protocol): rule 3, `above_every`, against
  each method's mean over OGBench's 8 seeds.
- "OPOSM reaches the paper's table 1" (the paper's protocol) and "... table 4" (goals from the
  training data): rule 2, `reproduces`, the paper's rate taken as `EPISODES_MAZE2D` episodes
  (it states no count for the ant; the maze2d count, the lower end). The paper ran D4RL's
  antmaze-*-diverse data and its own goals: a reference, not the same benchmark.
- "OPOSM reaches goals more often than LLP" (the paper's table 1; our LLP on the same tasks,
  OGBench's protocol): rule 1, `versus`; the paper's LLP rows (`TABLE1_LLP`)
  beside it.
- Figure 5, "OPOSM keeps more of its success under mass changes than the expert": rule 5,
  `versus` on each agent's success pooled over the perturbed factors (`off_nominal`).
- Table 3, EM against naive VI: `pipeline.reporting.em_vi` (rule 4, `separated`, on the TAWM's
  per-seed calibration and the optimism gap; rule 1, `versus`, on success pooled over seeds),
  judged once both methods ran the same seeds, at least `em_vi.MIN_SEEDS` each.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pipeline.errors import UserError
from pipeline.evaluation.published import (
    EPISODES_MAZE2D,
    FIGURE5,
    FIGURE5_FACTORS,
    OGBENCH,
    OGBENCH_SEEDS,
    TABLE1,
    TABLE1_LLP,
    TABLE3,
    TABLE4,
)
from pipeline.reporting import em_vi
from pipeline.reporting.common import (
    FAILS,
    HOLDS,
    INCONCLUSIVE,
    above_every,
    kept_share,
    mean_std,
    off_nominal,
    percent,
    points,
    rate,
    read,
    reproduces,
    stamp_text,
    train_speed,
    versus,
    write_report,
)
from pipeline.reporting.common import write_page as write_results_page

# The page's order: OGBench's navigate datasets by their maze, then its stitch and explore ones.
MAZES = ("medium", "large", "giant", "medium-stitch", "large-stitch", "giant-stitch",
         "medium-explore", "large-explore")  # fmt: skip
NAVIGATE = ("medium", "large", "giant")  # the paper's D4RL antmazes have these mazes' counterparts
TASKS = [f"ogbench-task{i}" for i in range(1, 6)]
OVERALL = "ogbench"
OGBENCH_STEPS = 1000  # OGBench's episode limit on its ant mazes
MASS_RUN = "mass"  # runs named mass<factor> (`deploy.mass_scale`): the figure-5 sweep
TABLE3_RUN = "table3-"  # runs table3-<method>-seed<seed> (stages em_vi_*): table 3, EM vs VI
AGENT_ORDER = ("oposm", "llp", "gcbc", "expert")  # the rows' order; other agents after
NEAR_M = 4.0  # one OGBench ant-maze cell: "near the goal" when sorting the failed episodes
FAILURES = ("fell", "late", "near", "far")  # `failures`' kinds, in the page's order


def ogbench_name(maze: str) -> str:
    """OGBench's dataset: `medium` -> antmaze-medium-navigate, `medium-stitch` as it is named."""
    return f"antmaze-{maze}" if "-" in maze else f"antmaze-{maze}-navigate"


def paper_name(maze: str) -> str:
    """The paper's D4RL counterpart of a navigate maze (the others have none: the paper's tables
    hold nothing for them)."""
    return f"antmaze-{maze}-diverse"


# --- reading the runs ---------------------------------------------------------------------------


def protocols(row: Mapping[str, Any], max_steps: int) -> dict[str, dict[str, Any] | None]:
    """One deploy task row -> its `rate` under OGBench's protocol (the first 1000 steps) and under
    the paper's (the whole episode, when it ran longer than 1000 steps; else None)."""
    n = row["episodes"]
    if max_steps <= OGBENCH_STEPS:
        return {"ogbench": rate(row["successes"], n), "paper": None}
    within = row["within_steps"][str(OGBENCH_STEPS)]
    return {"ogbench": rate(within["successes"], n), "paper": rate(row["successes"], n)}


def _runs(root: Path) -> list[tuple[str, dict[str, Any]]]:
    paths = [_deploy_dir(root, "deploy") / "report.json"]
    paths += sorted((root / "runs").glob("*/reports/deploy/report.json"))
    found = []
    for path in paths:
        report = read(path)
        if report:
            name = path.parents[2].name if path.parents[2] != root else "deploy"
            found.append((name, report))
    return found


def _deploy_dir(root: Path, run: str) -> Path:
    """Where run `run`'s deploy reports are (`deploy`: the data root's own, unnamed run)."""
    return (root if run == "deploy" else root / "runs" / run) / "reports" / "deploy"


def failures(episodes: list[Mapping[str, Any]]) -> dict[str, int]:
    """OGBench's failures (no success within its 1000 steps) sorted by what became of them:
    `fell` (the ant fell before step 1000), `late` (it reached the goal later in a longer
    episode), `near` (it came within one maze cell, NEAR_M, of the goal and did not reach it),
    `far` (it never came that near)."""
    out = dict.fromkeys(FAILURES, 0)
    for e in episodes:
        reached = e.get("steps_to_goal")
        if reached is not None and reached <= OGBENCH_STEPS:
            continue
        fell = e.get("fell_at")
        if fell is not None and fell <= OGBENCH_STEPS:
            out["fell"] += 1
        elif reached is not None:
            out["late"] += 1
        elif e.get("min_distance", float("inf")) <= NEAR_M:
            out["near"] += 1
        else:
            out["far"] += 1
    return out


def _agents(root: Path, runs: list[tuple[str, dict[str, Any]]]) -> list[dict[str, Any]]:
    """Every agent of every run on OGBench's tasks (mass sweeps aside): its rates per task under
    both protocols, its falls and, where the run kept its episode records (`episodes.json`),
    its failures sorted; an agent met again is named after its run."""
    rows, seen = [], set()
    # a run named after its agent (runs/oposm/) first: that agent's row; others after, by name
    named_first = sorted(runs, key=lambda r: (r[0] not in r[1].get("by_agent", {}), r[0]))
    for run, report in named_first:
        if run.startswith((MASS_RUN, TABLE3_RUN)) or OVERALL not in report.get("tasks", []):
            continue
        records = read(_deploy_dir(root, run) / "episodes.json") or []
        for agent, by_task in report["by_agent"].items():
            name = agent if agent not in seen else f"{agent} (run {run})"
            seen.add(agent)
            tasks = {t: protocols(by_task[t], report["max_steps"]) for t in [*TASKS, OVERALL]
                     if t in by_task}  # fmt: skip
            episodes = [e for e in records
                        if e.get("agent") == agent and e.get("task") in TASKS]  # fmt: skip
            rows.append({"agent": name, "run": run, "max_steps": report["max_steps"],
                         "episodes_per_task": report["episodes_per_task"],
                         "fallen": by_task[OVERALL].get("fallen"), "tasks": tasks,
                         "failures": failures(episodes) if episodes else None})  # fmt: skip
    order = {agent: i for i, agent in enumerate(AGENT_ORDER)}
    return sorted(rows, key=lambda r: order.get(r["agent"].split(" (run ")[0], len(order)))


def _random_goal(runs: list[tuple[str, dict[str, Any]]]) -> list[dict[str, Any]]:
    """Runs on goals from the training data (`deploy.tasks: [random_goal]`): each agent's rate
    under both protocols, its final distance and falls."""
    rows = []
    for run, report in runs:
        if report.get("tasks") != ["random_goal"]:
            continue
        for agent, by_task in report["by_agent"].items():
            row = by_task["random_goal"]
            rows.append({"run": run, "agent": agent, **protocols(row, report["max_steps"]),
                         "final_distance_mean": row.get("final_distance_mean"),
                         "fallen": row.get("fallen")})  # fmt: skip
    return rows


def _mass_sweep(runs: list[tuple[str, dict[str, Any]]]) -> dict[str, dict[str, Any]] | None:
    """agent -> mass factor (a string) -> its pooled `rate` on OGBench's tasks (OGBench's
    protocol)."""
    sweep: dict[str, dict[str, Any]] = {}
    for run, report in runs:
        if not run.startswith(MASS_RUN):
            continue
        for agent, by_task in report["by_agent"].items():
            rates = protocols(by_task[OVERALL], report["max_steps"])
            sweep.setdefault(agent, {})[str(float(report["mass_scale"]))] = rates["ogbench"]
    for agent in sweep:
        sweep[agent] = dict(sorted(sweep[agent].items(), key=lambda kv: float(kv[0])))
    return sweep or None


def collect(root: Path) -> dict[str, Any]:
    """One maze's data root: its stage reports, its agents, goals from the data (its mass runs
    are `figure5_report`'s)."""
    reports = root / "reports"
    out: dict[str, Any] = {"data_root": root.as_posix()}
    for stage in ("ingest", "segment", "dynamics", "validate"):
        out[stage] = read(reports / stage / "report.json")
    out["train"] = read(reports / "train" / "metrics.json")
    runs = _runs(root)
    out["agents"] = _agents(root, runs)
    out["random_goal"] = _random_goal(runs)
    return out


# --- verdicts -----------------------------------------------------------------------------------


def _agent(maze: Mapping[str, Any], name: str) -> dict[str, Any] | None:
    return next((a for a in maze["agents"] if a["agent"] == name), None)


def verdicts(name: str, maze: Mapping[str, Any]) -> list[dict[str, Any]]:
    """Every claim this maze's runs can judge: its words, the verdict, the interval (points)."""
    out = []
    oposm = _agent(maze, "oposm")
    table = OGBENCH.get(ogbench_name(name))
    if oposm and table:
        ours = oposm["tasks"][OVERALL]["ogbench"]
        word, method, interval = above_every(ours, table, OGBENCH_SEEDS)
        out.append({"claim": f"OPOSM is above every published method on {ogbench_name(name)} "
                    "(OGBench's protocol)", "verdict": word, "interval": interval,
                    "detail": f"OPOSM {percent(ours['rate'], *ours['ci95'])} vs {method} "
                    f"{mean_std(*table[method])} (the method deciding it)"})  # fmt: skip
    for number, what, published, ours in (
        (1, "its fixed goal", TABLE1, oposm and oposm["tasks"][OVERALL]["paper"]),
        (4, "random goals", TABLE4,
         next((r["paper"] for r in maze["random_goal"] if r["agent"] == "oposm"), None)),
    ):  # fmt: skip
        row = published.get(paper_name(name))
        if not (ours and row):
            continue
        mean, _ = row["oposm"]
        word, interval = reproduces(ours, mean, EPISODES_MAZE2D)
        out.append({"claim": f"OPOSM reaches the paper's table {number} ({paper_name(name)}, "
                    f"{what}; the paper's protocol)", "verdict": word, "interval": interval,
                    "detail": f"OPOSM {percent(ours['rate'], *ours['ci95'])} vs the paper's "
                    f"{percent(mean)} (as {EPISODES_MAZE2D} episodes)"})  # fmt: skip
    llp = _agent(maze, "llp")
    if oposm and llp:
        a, b = oposm["tasks"][OVERALL]["ogbench"], llp["tasks"][OVERALL]["ogbench"]
        word, interval = versus(a, b)
        their_oposm = TABLE1.get(paper_name(name))
        their_llp = TABLE1_LLP.get(paper_name(name))
        theirs = (f"; the paper's table 1 ({paper_name(name)}): OPOSM "
                  f"{percent(their_oposm['oposm'][0])} vs LLP {percent(their_llp[0])}"
                  if their_oposm and their_llp else "")  # fmt: skip
        out.append({"claim": f"OPOSM reaches goals more often than LLP on {ogbench_name(name)} "
                    "(the paper's table 1; OGBench's protocol, the same tasks)", "verdict": word,
                    "interval": interval,
                    "detail": f"OPOSM {percent(a['rate'], *a['ci95'])} vs LLP "
                    f"{percent(b['rate'], *b['ci95'])}{theirs}"})  # fmt: skip
    return out


def mass_verdicts(sweep: Mapping[str, Mapping[str, Any]] | None) -> list[dict[str, Any]]:
    """Figure 5's claim on a mass sweep (`_mass_sweep`), when both OPOSM and the expert ran."""
    sweep = sweep or {}
    if not ("oposm" in sweep and "expert" in sweep):
        return []
    a, b = off_nominal(sweep["oposm"]), off_nominal(sweep["expert"])
    if not (a and b):
        return []
    word, interval = versus(a, b)
    return [{"claim": "OPOSM keeps more of its success under mass changes than the expert "
             "(paper figure 5)", "verdict": word, "interval": interval,
             "detail": f"off x1, pooled: OPOSM {percent(a['rate'], *a['ci95'])} vs expert "
             f"{percent(b['rate'], *b['ci95'])}"}]  # fmt: skip


# --- rendering ----------------------------------------------------------------------------------


def _cell(r: Mapping[str, Any] | None) -> str:
    return "–" if r is None else percent(r["rate"], *r["ci95"], digits=0)


def _agent_rows(agents: list[dict[str, Any]]) -> list[str]:
    lines = ["| agent | episodes per task | " + " | ".join(f"task {i}" for i in range(1, 6))
             + " | overall, OGBench (1000 steps) | overall, paper (2000 steps) | fell |",
             "|---" * 10 + "|"]  # fmt: skip
    for a in agents:
        t = a["tasks"]
        cells = [_cell(t[k]["ogbench"]) if k in t else "–" for k in TASKS]
        overall = t[OVERALL]
        fell = "–" if a["fallen"] is None else str(a["fallen"])
        lines.append(f"| {a['agent']} | {a['episodes_per_task']} | " + " | ".join(cells)
                     + f" | **{_cell(overall['ogbench'])}** | {_cell(overall['paper'])} "
                     f"| {fell} |")  # fmt: skip
    return lines


def _failure_lines(agents: list[dict[str, Any]]) -> list[str]:
    """The failed episodes under OGBench's protocol, sorted (`failures`), for the agents whose
    episode records the report read; nothing when none has them."""
    rows = [a for a in agents if a.get("failures")]
    if not rows:
        return []
    lines = ["", "Where the failures under OGBench's protocol end (episodes; `fell`: the ant fell "
             "within the 1000 steps; `late`: it reached the goal after them; `near`: it came "
             f"within {NEAR_M:g} m, one maze cell, and did not reach it; `far`: never that near):",
             "", "| agent | failed | fell | late | near | far |", "|---" * 6 + "|"]  # fmt: skip
    for a in rows:
        f = a["failures"]
        lines.append(f"| {a['agent']} | {sum(f.values())} | "
                     + " | ".join(str(f[k]) for k in FAILURES) + " |")  # fmt: skip
    return lines


def _expert_check_row(expert: Mapping[str, Any], maze: str) -> str | None:
    check = expert.get("quality", {}).get("mazes", {}).get(f"antmaze-{maze}-v0")
    if not check:
        return None
    cells = [_cell(rate(t["successes"], t["episodes"])) for t in check["tasks"]]
    o = check["overall"]
    n = check["tasks"][0]["episodes"]
    return (f"| expert, noise-free (`oposm expert check`) | {n} | " + " | ".join(cells)
            + f" | **{_cell(rate(o['successes'], o['episodes']))}** | – | – |")  # fmt: skip


def _ladder(maze: Mapping[str, Any]) -> list[str]:
    lines = []
    validate = maze.get("validate")
    if validate:
        replay = [(k, v) for k, v in validate.get("posterior", {}).items()
                  if "replay_error_mean" in v]  # fmt: skip
        if replay:
            lines += [
                "(a) Skill fidelity: the posterior's skills of held-out recorded windows, "
                "executed by the policy in MuJoCo from the recorded start; mean x-y "
                "distance to the recorded end (m), against the TAWM's prediction and "
                "against no model (the end = the start):",
                "",
                "| skills | steps | executed | TAWM | no model |",
                "|---|---|---|---|---|",
            ]
            lines += [
                f"| {k.split('_')[1]} | {v['steps']} | {v['replay_error_mean']:.2f} | "
                f"{v['tawm_recorded_error_mean']:.2f} | "
                f"{v['no_model_recorded_error_mean']:.2f} |"
                for k, v in replay
            ]
            lines.append("")
        lines += [f"(b) Open loop with prior skills from {validate['starts']} held-out starts: "
                  "mean x-y error of the predicted end (m); paper figure 4 is antmaze-large:", "",
                  "| skills | steps | TAWM | single-step model | no model | TAWM within 1 sigma |",
                  "|---|---|---|---|---|---|"]  # fmt: skip
        lines += [f"| {k.split('_')[1]} | {v['steps']} | {v['tawm_error_mean']:.2f} | "
                  f"{v['single_step_error_mean']:.2f} | {v['no_model_error_mean']:.2f} | "
                  f"{percent(v['tawm_within_1sigma'], digits=0)} % |"
                  for k, v in validate["prior"].items()]  # fmt: skip
        lines.append("")
    for r in maze.get("random_goal", []):
        dist = r["final_distance_mean"]
        lines.append(f"(c) Goals from the training data (`random_goal`, run `{r['run']}`, the "
                     f"development metric): {r['agent']} {_cell(r['ogbench'])} % within 1000 "
                     f"steps, {_cell(r['paper'])} % within 2000, of {r['ogbench']['episodes']} "
                     "episodes; mean final distance "
                     + ("–" if dist is None else f"{dist:.2f} m")
                     + f"; fell in {'–' if r['fallen'] is None else r['fallen']}.")  # fmt: skip
    return lines + ([""] if maze.get("random_goal") else [])


def _data_lines(name: str, maze: Mapping[str, Any]) -> list[str]:
    lines = []
    ingest, train = maze.get("ingest"), maze.get("train")
    if ingest:
        # navigate: a new goal on each reach; stitch: one goal per episode, every step there counts
        goals = (f"{ingest.get('goals_per_1000_steps', float('nan')):.1f} goals reached per 1000 "
                 "steps" if name in NAVIGATE else
                 f"{ingest.get('episodes_reaching_goal', float('nan')):.0f} episodes reach their "
                 "goal")  # fmt: skip
        lines.append(f"- Data: {ingest['episodes']:.0f} episodes, {ingest['steps']:.0f} steps; "
                     f"the ant fallen or upside down in {ingest.get('fallen_steps', 0):.0f} steps "
                     f"({ingest.get('fallen_episodes', 0):.0f} episodes); {goals}.")  # fmt: skip
    if train:
        val = train["val"]
        lines.append(
            f"- Training (EM): {train['steps']} steps ({train_speed(train)} on "
            f"{train.get('device')}); "
            f"published checkpoint by `{train['select']}` at step {train['best_step']}; "
            f"validation s_T NLL {val['st_nll']:.2f} (posterior skill), "
            f"{val['st_nll_prior']:.2f} (prior skills); KL(q || prior) "
            f"{val.get('kl', float('nan')):.1f} nats at the last evaluation."
        )
    return lines


def _mass_rows(sweep: Mapping[str, Mapping[str, Any]]) -> list[str]:
    agents = list(sweep)
    factors = sorted({f for a in agents for f in sweep[a]}, key=float)
    lines = ["| mass factor | " + " | ".join(agents) + " | paper: OPOSM | paper: expert |",
             "|---" * (len(agents) + 3) + "|"]  # fmt: skip
    for f in factors:
        cells = [_cell(sweep[a].get(f)) for a in agents]
        i = FIGURE5_FACTORS.index(float(f)) if float(f) in FIGURE5_FACTORS else None
        cells += ["–" if i is None else percent(FIGURE5[k][i], digits=0)
                  for k in ("oposm", "expert")]  # fmt: skip
        lines.append(f"| x{float(f):g} | " + " | ".join(cells) + " |")
    kept = {a: k for a in agents if (k := kept_share(_as_rates(sweep[a]))) is not None}
    if kept:
        lines += ["", "Mean success over the perturbed factors as a share of the success at x1 "
                  "(descriptive): " + ", ".join(f"{a} {percent(k, digits=0)} %"
                                                for a, k in kept.items()) + "."]  # fmt: skip
    return lines


def _as_rates(by_factor: Mapping[str, Any]) -> dict[str, Any]:
    return {f: r for f, r in by_factor.items() if r is not None}


def _published_line(name: str) -> str:
    table = OGBENCH.get(ogbench_name(name))
    parts = []
    if table:
        parts.append(
            f"OGBench's paper ({ogbench_name(name)}, {OGBENCH_SEEDS} seeds, its "
            "protocol): " + ", ".join(f"{m} {mean_std(*v)}" for m, v in table.items())
        )
    own = [f"table {n} ({what}) {mean_std(*t[paper_name(name)]['oposm'], digits=1)}"
           for n, what, t in ((1, "fixed goal", TABLE1), (4, "random goals", TABLE4))
           if paper_name(name) in t]  # fmt: skip
    if own:
        parts.append(f"the paper (D4RL {paper_name(name)}, its own goals and protocol): "
                     + ", ".join(own))  # fmt: skip
    return ("Published: " + "; ".join(parts) + ".") if parts else "No published number quoted."


_WORDS = {HOLDS: "holds", FAILS: "does not hold", INCONCLUSIVE: "inconclusive"}


def _table3_lines(name: str, table3: Mapping[str, Any]) -> list[str]:
    runs = table3["runs"]
    seeds = sorted({seed for by_seed in runs.values() for seed in by_seed}, key=int)
    published = TABLE3.get(paper_name(name))
    theirs = (f" The paper's table 3 ({paper_name(name)}, its goals and protocol): EM "
              f"{mean_std(*published['em'], digits=1)}, naive VI "
              f"{mean_std(*published['vi'], digits=1)}." if published else "")  # fmt: skip
    lines = [f"Table 3 on this maze: EM against naive VI (`train.method`), seeds "
             f"{', '.join(seeds) or 'none yet'}, the same data, recipe and E-step KL "
             f"(`train.e_kl: {table3['e_kl']}`); each run validated (the TAWM against real "
             "outcomes of one prior skill: its NLL, the share within 1 sigma, the x-y error) "
             f"and deployed on OGBench's five tasks ({table3['episodes_per_run']} episodes per "
             f"run, OGBench's protocol; success % with its 95 % Wilson interval; gap: the "
             f"optimism gap in m).{theirs}", "",
             *em_vi.tables({ogbench_name(name): runs})]  # fmt: skip
    if not table3["verdicts"]:
        lines += ["", f"No verdict yet: each method needs the same {em_vi.MIN_SEEDS} or more "
                  "seeds."]  # fmt: skip
    lines += ["", f"Table 3's report: `results/antmaze/{name}-table3.json`, "
              f"{stamp_text(table3['stamp'])}. Its commands:", "", "```bash",
              *table3.get("commands", []), "```"]  # fmt: skip
    return lines


def render(results: Mapping[str, Any]) -> str:
    expert = results["expert"]
    made = ("Made by `uv run dvc repro experiments/antmaze/dvc.yaml` (each maze's commands in "
            "its section)" if results["stamp"].get("dvc") else
            "Made by `oposm report antmaze page` from the mazes' reports")  # fmt: skip
    lines = [
        "# OGBench ant mazes: OPOSM beside OGBench's published table and the paper's",
        "",
        f"{made}; {stamp_text(results['stamp'])}. Every setting: `params-ogbench-antmaze-<maze>"
        ".yaml` (an overlay of `params.yaml`); every number: `antmaze.json`.",
        "",
        "## Verdicts",
        "",
    ]
    if not results["mazes"]:
        lines.append("- None yet: no maze has a report.")
    for checks in results["verdicts"].values():
        lines += [f"- {c['claim']}: **{_WORDS[c['verdict']]}**: {c['detail']}"
                  + (f"; difference {points(c['interval'])} points." if c.get("interval")
                     else ".") for c in checks]  # fmt: skip
    lines += [
        "",
        "## Protocol",
        "",
        "- Environment: OGBench's `antmaze-<maze>-v0` (its locomaze: the D4RL ant, gear 30, 0.1 s "
        "per step), 29-dim state (qpos + qvel), 8 torques.",
        "- Tasks: its five evaluation tasks per maze (start and goal cells with its noise), "
        "success within 0.5 of the goal. OGBench's protocol: at most 1000 steps. The paper's: "
        "its code's 2000-step episodes, from the same run (an episode runs the same up to 1000 "
        "steps whatever its limit). The planner gets the goal as `[x, y]`; GCBC gets a full goal "
        "observation (a standing ant at the goal).",
        "- Data: OGBench's `navigate` recipe run here with our expert in the place of OGBench's "
        "(BFS oracle direction -> our direction-commanded SAC actor -> + N(0, 0.2), clipped; a "
        "new goal on each reach; 1001-step episodes); its `stitch` recipe for the `-stitch` "
        "datasets (the same controller, 201-step episodes, each to a goal 4 cells away).",
        f"- Expert: `experts/ant/actor.safetensors`, {expert.get('steps')} SAC steps "
        f"({expert.get('sac_phases')}).",
        "- Intervals: 95 % Wilson; verdicts by the rules of `pipeline/reporting/common.py` "
        "(docs/experiments.md).",
        "",
    ]
    for name, maze in results["mazes"].items():
        lines += [f"## {ogbench_name(name)}", "", *_data_lines(name, maze)]
        lines += [f"- {note}" for note in maze.get("notes", [])]
        lines += ["", "The ladder (each step needs the one before):", "", *_ladder(maze)]
        if maze["agents"]:
            lines += ["(d) OGBench's five tasks, success % (95 % Wilson interval):", "",
                      *_agent_rows(maze["agents"])]  # fmt: skip
        else:
            lines += ["(d) OGBench's five tasks: not deployed yet.", ""]
        row = _expert_check_row(expert, name)
        if row:
            if not maze["agents"]:
                lines += _agent_rows([])
            lines.append(row)
        lines += _failure_lines(maze["agents"])
        fig5 = maze.get("figure5")
        if fig5 and fig5.get("mass_sweep"):
            lines += ["", "Robustness to the ant's mass (paper figure 5: every body's mass and "
                      "inertia times the factor, the models unchanged), success % on OGBench's "
                      f"five tasks pooled ({fig5['episodes_per_factor']} episodes per factor and "
                      "agent), OGBench's protocol, beside the paper's (antmaze-large, its "
                      "protocol):", "", *_mass_rows(fig5["mass_sweep"]), "",
                      f"The sweep's report: `results/antmaze/{name}-figure5.json`, "
                      f"{stamp_text(fig5['stamp'])}. Its commands:", "", "```bash",
                      *fig5.get("commands", []), "```"]  # fmt: skip
        table3 = maze.get("table3")
        if table3:
            lines += ["", *_table3_lines(name, table3)]
        lines += ["", _published_line(name), ""]
        lines += [f"This maze's report: `results/antmaze/{name}.json`, "
                  f"{stamp_text(maze['stamp'])}. Its commands:", "", "```bash",
                  *maze.get("commands", []), "```", ""]  # fmt: skip
    return "\n".join(lines)


# --- the report ---------------------------------------------------------------------------------


def expert_info(actor: Mapping[str, Any]) -> dict[str, Any]:
    """What the report says of the shipped expert (`experts/ant/actor.json`)."""
    info = actor.get("info", {})
    phases = ", then ".join(
        f"from step {p['from_step']}: action noise {p['action_noise']}"
        + (", episode ends on a flip" if p["terminate_upside_down"] else "")
        for p in info.get("sac", {}).get("phases", [])
    )
    return {"steps": info.get("steps"), "sac_phases": phases or "OGBench's recipe",
            "quality": info.get("quality", {})}  # fmt: skip


def runs_json(mazes: Mapping[str, Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Every agent's successes per task, flat: maze, agent, protocol, tasks -> episodes and
    successes."""
    out = []
    for name, maze in mazes.items():
        for a in maze["agents"]:
            for protocol in ("ogbench", "paper"):
                tasks = {t: {"episodes": r[protocol]["episodes"],
                             "successes": r[protocol]["successes"]}
                         for t, r in a["tasks"].items() if r[protocol]}  # fmt: skip
                if tasks:
                    out.append({"maze": name, "dataset": ogbench_name(name), "agent": a["agent"],
                                "protocol": protocol, "tasks": tasks})  # fmt: skip
    return out


def maze_report(
    name: str, root: Path, notes: list[str], commands: list[str], stamp: Mapping[str, Any]
) -> dict[str, Any]:
    """One maze's report (stage `maze@<maze>`, `results/antmaze/<maze>.json`): what its data root
    holds (`collect`), its verdicts, its notes, the commands that made it and where."""
    if name not in MAZES:
        raise UserError(f"maze {name!r} is not one of {MAZES}")
    maze = collect(root) | {"notes": list(notes), "commands": list(commands)}
    return {"maze": name, "stamp": dict(stamp), **maze, "verdicts": verdicts(name, maze)}


def figure5_report(
    name: str, root: Path, commands: list[str], stamp: Mapping[str, Any]
) -> dict[str, Any]:
    """A maze's mass sweep (stage `figure5`, `results/antmaze/<maze>-figure5.json`) from the runs
    named `mass<...>` of its data root: agent -> factor -> success, figure 5's verdict."""
    if name not in MAZES:
        raise UserError(f"maze {name!r} is not one of {MAZES}")
    runs = [(run, report) for run, report in _runs(root) if run.startswith(MASS_RUN)]
    if not runs:
        raise UserError(f"{root / 'runs'}: no mass<...>/reports/deploy; run the mass@ stages")
    sweep = _mass_sweep(runs)
    return {"maze": name, "stamp": dict(stamp), "mass_sweep": sweep,
            "episodes_per_factor": max(len(TASKS) * r["episodes_per_task"] for _, r in runs),
            "verdicts": mass_verdicts(sweep), "commands": list(commands)}  # fmt: skip


def table3_report(
    name: str,
    root: Path,
    e_kl: str,
    commands: list[str],
    stamp: Mapping[str, Any],
) -> dict[str, Any]:
    """A maze's table 3 (stage `table3`, `results/antmaze/<maze>-table3.json`) from the runs
    `table3-<method>-seed<seed>` of its data root: each finished run's numbers
    (`em_vi.run_numbers`), and the paper's predictions once both methods ran the same seeds."""
    if name not in MAZES:
        raise UserError(f"maze {name!r} is not one of {MAZES}")
    runs: dict[str, dict[str, Any]] = {method: {} for method in em_vi.METHODS}
    episodes = set()
    for method in em_vi.METHODS:
        prefix = f"{TABLE3_RUN}{method}-seed"
        for path in sorted((root / "runs").glob(f"{prefix}*")):
            seed = path.name.removeprefix(prefix)
            numbers = em_vi.run_numbers(path) if seed.isdigit() else None
            if numbers is not None:
                runs[method][seed] = numbers
                episodes.add(numbers["success"]["episodes"])
    if not any(runs.values()):
        raise UserError(f"{root / 'runs'}: no {TABLE3_RUN}<method>-seed<seed>/ with validate and "
                        "deploy reports; run the em_vi_* stages")  # fmt: skip
    if len(episodes) > 1:
        raise UserError(f"{root / 'runs'}: the {TABLE3_RUN}* runs deployed {sorted(episodes)} "
                        "episodes; rerun them alike (em_vi.episodes)")  # fmt: skip
    seeds = [set(runs[m]) for m in em_vi.METHODS]
    judged = all(s == seeds[0] for s in seeds) and len(seeds[0]) >= em_vi.MIN_SEEDS
    claims = em_vi.claims(f"{ogbench_name(name)} ant", runs["em"], runs["vi"]) if judged else []
    verdicts = [{"claim": c["claim"], "verdict": c["verdict"], "interval": None,
                 "detail": c["numbers"]} for c in claims]  # fmt: skip
    return {"maze": name, "stamp": dict(stamp), "e_kl": e_kl, "episodes_per_run": episodes.pop(),
            "runs": runs, "verdicts": verdicts, "commands": list(commands)}  # fmt: skip


def page(
    reports: list[Mapping[str, Any]],
    expert: Mapping[str, Any],
    stamp: Mapping[str, Any],
    figure5: list[Mapping[str, Any]] = (),
    table3: list[Mapping[str, Any]] = (),
) -> dict[str, Any]:
    """The page's JSON (stage `report`, `results/antmaze.json`) from the mazes' reports and
    their mass sweeps', in `MAZES`' order: the mazes, their verdicts, the flat runs, the
    published numbers."""
    mazes = {r["maze"]: dict(r) for r in sorted(reports, key=lambda r: MAZES.index(r["maze"]))}
    attached = (("figure5", "the mass sweep", figure5), ("table3", "table 3", table3))
    for key, what, extras in attached:
        for extra in extras:
            if extra["maze"] not in mazes:
                raise UserError(f"{what} of {extra['maze']} has no maze report beside it; "
                                f"add results/antmaze/{extra['maze']}.json")  # fmt: skip
            maze = mazes[extra["maze"]]
            maze[key] = dict(extra)
            maze["verdicts"] = [*maze["verdicts"], *extra["verdicts"]]
    published = {
        ogbench_name(m): {k: [round(100 * a), round(100 * b)] for k, (a, b) in t.items()}
        for m in MAZES if (t := OGBENCH.get(ogbench_name(m)))
    }  # fmt: skip
    return {
        "what": "OPOSM on OGBench's ant mazes, beside OGBench's published table and the paper's",
        "stamp": dict(stamp),
        "expert": dict(expert),
        "mazes": mazes,
        "verdicts": {name: maze["verdicts"] for name, maze in mazes.items()},
        "runs": runs_json(mazes),
        "published": published,
        "paper": {
            paper_name(m): {
                **{
                    f"table{n}": list(t[paper_name(m)]["oposm"])
                    for n, t in ((1, TABLE1), (4, TABLE4))
                    if paper_name(m) in t
                },
                **(
                    {"table3": {k: list(v) for k, v in TABLE3[paper_name(m)].items()}}
                    if paper_name(m) in TABLE3
                    else {}
                ),
            }
            for m in NAVIGATE
        },  # fmt: skip
    }


def write_maze(path: Path, report: Mapping[str, Any]) -> None:
    """A maze's report as JSON."""
    write_report(path, report)


def write_page(out: Path, results: Mapping[str, Any]) -> None:
    """`out/antmaze.json` and `out/antmaze.md`."""
    write_results_page(out, "antmaze", results, render(results))
