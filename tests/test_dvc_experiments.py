"""The experiments pipelines beside the main job: experiments/dvc.yaml (the paper's experiments)
and experiments/ogbench/dvc.yaml (OGBench's point mazes, results/ogbench-point.md).

Fast: the OGBench pipeline parses, each data root runs its params variant with its whole chain
as params deps and the dataset name its outputs are under, each run reads the models of its agent;
a committed lock that no longer matches its pipeline's params, code or results fails (DVC's own
status of each dependency, nothing run). Slow: one dataset on tiny settings through the real
`dvc repro` (its target, then the report), and two experiments on two workers of DVC's queue,
whose outputs a later `dvc repro` restores from the shared run cache.
"""

from __future__ import annotations

import functools
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from pipeline.config import load_params, params_files
from pipeline.reporting import ogbench_point
from pipeline.reporting.common import lock_digest

ROOT = Path(__file__).resolve().parents[1]
OGB = "experiments/ogbench/dvc.yaml"
VARS = "experiments/ogbench/params.yaml"


def _plan() -> dict:
    return yaml.safe_load((ROOT / VARS).read_text())


def _overrides(*texts: str) -> list[str]:
    """The `section.key=value` of `-S` options in command-line fragments."""
    tokens = shlex.split(" ".join(texts))
    return [tokens[i + 1] for i, t in enumerate(tokens) if t == "-S"]


def test_dvc_reads_the_ogbench_pipeline():
    command = [sys.executable, "-m", "dvc", "stage", "list", OGB]
    out = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    names = {line.split()[0].split(":")[1] for line in out.stdout.splitlines() if line.strip()}
    plan = _plan()
    assert {f"dataset@{root}" for root in plan["datasets"]} <= names
    assert {f"deploy@{run}" for run in plan["runs"]} <= names
    assert {"ingest@giant-stitch5k", "train@teleport", "bc@giant", "gcbc@medium", "report"} <= names


def test_each_data_root_runs_its_variant_and_declares_its_whole_chain():
    plan = _plan()
    tables = set()
    for root, d in plan["datasets"].items():
        chain = [p.relative_to(ROOT).as_posix() for p in params_files(ROOT / d["params"])]
        assert chain[-1] == "params.yaml" and chain[0] == d["params"], chain
        assert len(d["overlays"]) == 3, f"{root}: three overlay slots (dvc.yaml lists three)"
        assert list(dict.fromkeys(d["overlays"])) == chain[-2::-1], f"{root}: {d['overlays']}"
        params = load_params(ROOT / d["params"], _overrides(d["set"], *plan["set"].values()))
        assert params.ingest.name == d["name"] and d["root"] == root, root
        assert d["dataset"] in ogbench_point.DATASETS, root
        tables.add(d["dataset"])
        assert any(r["root"] == root for r in plan["runs"].values()), f"{root} has no run"
    assert tables == set(ogbench_point.DATASETS)  # every dataset of the report has a data root
    for section in ("train_on", "gcbc_on", "llp_on"):
        for root, d in plan[section].items():
            assert d == plan["datasets"][root], (section, root)


def test_each_run_reads_the_models_of_its_agent():
    plan = _plan()
    folders = set()
    for key, run in plan["runs"].items():
        d = plan["datasets"][run["root"]]
        assert {k: run[k] for k in d} == d, f"{key}: not its root's settings (<<: *{d['root']})"
        overrides = _overrides(run["set"], run["deploy"], plan["set"]["deploy"])
        params = load_params(ROOT / run["params"], overrides)
        (agent,) = params.deploy.agents
        name = run["name"]
        needs, trained = {
            "oposm": ([f"models/{name}"] * 2, "train_on"),
            "gcbc": ([f"models/{name}-gcbc"] * 2, "gcbc_on"),
            "llp": ([f"models/{name}-dynamics", f"models/{name}-bc"], "llp_on"),
            "expert": ([f"segments/{name}"] * 2, None),
        }[agent]
        assert run["needs"] == needs, key
        assert trained is None or run["root"] in plan[trained], f"{key}: no {trained} stage"
        assert params.deploy.tasks == ["ogbench"], key
        assert (run["root"], run["run"]) not in folders, f"{key}: a run folder used twice"
        folders.add((run["root"], run["run"]))


# stages a fresh lock may lack while they run (long runs over several days): pipeline -> (their
# name prefixes, what they are); once run, they are checked as any other
NOT_RUN_YET: dict[str, tuple[tuple[str, ...], str]] = {
    "experiments/manipulation/dvc.yaml": (
        tuple(f"{stage}@{d}" for stage in ("value", "deploy_value")
              for d in ("cube-single-play", "scene-play")),
        "OPOSM with a learned value on the datasets whose data roots are rebuilt first",
    ),
    "experiments/antmaze/dvc.yaml": (
        tuple(f"{stage}@{maze}" for maze in ("medium-explore", "large-explore") for stage in (
            "ingest", "segment", "train", "dynamics", "bc", "gcbc", "validate", "deploy",
            "deploy_expert", "deploy_gcbc", "deploy_random_goal", "deploy_llp", "maze")
            if (stage, maze) != ("ingest", "medium-explore")),
        "the explore datasets: their chains run stage by stage (hours on 2 CPU cores)",
    ),
}  # fmt: skip


def _stale(pipeline: str) -> list[str]:
    """What in `pipeline`'s committed lock no longer matches: stages it lacks or holds besides
    the pipeline's, changed commands, params and code (DVC's status of each; data deps and outputs
    under data/ are for `dvc status` where the data is), and committed outputs (results/) that
    differ from the ones it recorded."""
    return _stale_locks()[pipeline]


@functools.cache
def _stale_locks() -> dict[str, list[str]]:
    """`_stale` of every pipeline in `PIPELINES`, from one read of the repository's DVC files.

    DVC parses YAML in pure Python, and each params dependency reads its file again: the same few
    params files hundreds of times. Each text is parsed once here (a copy handed out each time,
    since DVC may change what it gets), which takes the check from about a minute to seconds."""
    import copy
    from unittest import mock

    from dvc.repo import Repo
    from dvc.utils.serialize import _yaml

    parsed: dict[tuple[str, str], object] = {}
    parse = _yaml.parse_yaml

    def parse_once(text, path, typ="safe"):
        if (text, typ) not in parsed:
            parsed[text, typ] = parse(text, path, typ=typ)
        return copy.deepcopy(parsed[text, typ])

    with (
        mock.patch.object(_yaml, "parse_yaml", parse_once),
        mock.patch("dvc.utils.strictyaml.parse_yaml", parse_once),
        Repo(str(ROOT)) as repo,
    ):
        return {pipeline: _stale_in(repo, pipeline) for pipeline in PIPELINES}


def _stale_in(repo, pipeline: str) -> list[str]:
    from dvc.dependency.param import ParamsDependency

    lock_path = (ROOT / pipeline).with_suffix(".lock")
    if not lock_path.exists():
        return [f"{lock_path.relative_to(ROOT)} does not exist"]
    lock = yaml.load(lock_path.read_text(), Loader=yaml.CSafeLoader)  # libyaml: its stage names
    locked = set((lock or {}).get("stages", {}))
    problems = []
    stages = [s for s in repo.index.stages if s.dvcfile.path == str(ROOT / pipeline)]
    problems += [f"{n}: in the lock, not in {pipeline}" for n in locked - {s.name for s in stages}]
    for stage in stages:
        if stage.name not in locked:
            if not stage.name.startswith(NOT_RUN_YET.get(pipeline, ((), ""))[0]):
                problems.append(f"{stage.name}: never run (not in the lock)")
            continue
        if stage.cmd_changed:
            problems.append(f"{stage.name}: its command changed")
        for entry in [*stage.deps, *stage.outs]:
            if entry.def_path.startswith("data/") or "${" in entry.def_path:
                continue
            if not isinstance(entry, ParamsDependency) and not entry.exists:
                problems.append(f"{stage.name}: {entry.def_path} is missing")
            elif status := entry.status():
                changed = _changed_params(entry) if isinstance(entry, ParamsDependency) else []
                problems += [f"{stage.name}: {{'{k}': '{how}'}}" for k, how in changed] or [
                    f"{stage.name}: {dict(status)}"
                ]
    return problems


def _changed_params(entry) -> list[tuple[str, str]]:
    """`(section.key, 'new' | 'modified' | 'deleted')` for each param of a params dependency
    that differs from its lock, nested sections spelled out to their leaves (`deploy.planner.
    iterations`), which RERUN_PENDING may name like code files."""
    return _diff(entry.hash_info.value, entry.read_params(), "")


def _diff(before, now, prefix: str) -> list[tuple[str, str]]:
    if isinstance(before, dict) and isinstance(now, dict):
        out = []
        for key in [*before, *(k for k in now if k not in before)]:
            name = f"{prefix}{key}"
            if key not in now:
                out += (
                    _diff(before[key], {}, name + ".")
                    if isinstance(before[key], dict)
                    else [(name, "deleted")]
                )
            elif key not in before:
                out += (
                    _diff({}, now[key], name + ".")
                    if isinstance(now[key], dict)
                    else [(name, "new")]
                )
            else:
                out += _diff(before[key], now[key], name + ".")
        return out
    return [] if before == now else [(prefix.removesuffix("."), "modified")]


# every experiments pipeline: its committed lock ran with today's params and code (NOT_RUN_YET's
# stages aside)
PIPELINES = (
    "experiments/dvc.yaml",
    "experiments/antmaze/dvc.yaml",
    "experiments/manipulation/dvc.yaml",
    OGB,
)

# Code edited since the experiments' locks were made, whose stages wait for a rerun (they take
# days of CPU): file -> what a rerun of a stage that runs it would change. A stage stale for any
# other reason fails, and so does an entry no stage is stale for any more (remove it once rerun).
RERUN_PENDING: dict[str, str] = {
    "stages/report.py": "wall-clock keys move out of reports and headlines into data/timings/",
    "stages/train.py": "no wall-clock keys in dvclive's logs and summary; the summary names the "
    "CPU arithmetic (MKL's strict mode: bits independent of the thread count)",
    "stages/dynamics.py": "the checkpoint's config.json holds no wall time",
    "stages/bc.py": "the checkpoint's config.json holds no wall time",
    "stages/deploy.py": "episodes.json holds no planning seconds",
    "stages/validate.py": "the report holds no seconds; a `recorded` section (the TAWM against "
    "held-out recorded windows) beside the MuJoCo rollouts",
    "pipeline/evaluation/recorded.py": "(new) validate's `recorded` section",
    "pipeline/viz/recorded.py": "(new) validate's recording without a simulator",
    "pipeline/evaluation/open_loop.py": "a function renamed; outputs unchanged",
    "pipeline/evaluation/open_loop_metrics.py": "validate's report holds no seconds",
    "pipeline/sources": "OGBench's manipulation .npz files import; other sources write the same "
    "MCAP; OGBench's puzzles (generated and imported), the cube and scene data unchanged",
    "pipeline/viz/maze.py": "recordings: a helper renamed (the bytes of .rrd files differ on "
    "every run anyway)",
    "pipeline/viz/overview.py": "recordings: success bars on a fixed 0-100 % scale",
    "pipeline/viz/manip.py": "recordings: manipulation episodes draw the arm, table, goals, "
    "legend; a puzzle's buttons and goal states (cube and scene recordings as before)",
    "pipeline/viz/manip_scene.py": "(new) the manipulation scene of the recordings; a puzzle's "
    "buttons (cube and scene recordings as before)",
    "pipeline/reporting/common.py": "reports read their stage's wall-clock timings from "
    "data/timings/ (same pages where those exist)",
    "pipeline/reporting/antmaze.py": "the training line says 'time not recorded' without "
    "timings; a maze's failed episodes sorted (fell, late, near, far) where its deploys kept "
    "their episode records",
    "pipeline/reporting/manipulation.py": "the training line says 'time not recorded' without "
    "timings; the page shows a dataset's ladder where there is one; the puzzles are datasets it "
    "knows (the page as before until they run)",
    "pipeline/planning": "(new) simulated.py, the oposm_sim agent; the other agents unchanged",
    "stages/manipulation_report.py": "a `ladder` subcommand and the page's --ladders; the "
    "datasets' reports unchanged",
    "pipeline/reporting/manipulation_ladder.py": "(new) the ladder of where object moves fail",
    "pipeline/value/network.py": "(new) the planner's optional learned value (value.weight 0, "
    "the default: the same plans)",
    "stages/oracle.py": "the report holds no wall time (timings/deploy.json); successes unchanged",
    "pipeline/reporting/manipulation_variant.py": "(new) a variant's report (stage variant@); "
    "the datasets' reports and ladders unchanged",
    "pipeline/envs/manipspace/data.py": "OGBench's puzzle recipe (button oracle, gripper closed; "
    "noisy: 20 % random actions); the cube and scene data unchanged",
    "pipeline/viz/manip_validate.py": "validate's view follows the gripper in a puzzle (no cube); "
    "the cube and scene views unchanged",
}
# The Franka kitchen joins the stages (every env spec may now be the kitchen's): the main job's
# stages rerun with these gave byte-identical outputs; listed until the stages rerun.
RERUN_PENDING |= {
    path: "the kitchen joins the stages (D4RL's task sets and score); maze and manipulation "
    "outputs unchanged"
    for path in (
        "pipeline/envs/kitchen.py", "pipeline/viz/kitchen.py", "pipeline/envs/spec.py",
        "pipeline/evaluation/episodes.py", "pipeline/evaluation/goals.py",
        "pipeline/evaluation/stats.py",
    )
}  # fmt: skip
# Moved without changing what runs (constants to pipeline/envs/ids.py, docstrings): the main
# job's stages rerun with them gave byte-identical outputs; listed until the stages rerun.
RERUN_PENDING |= {
    path: "unchanged outputs: constants moved to pipeline/envs/ids.py, imports, docstrings"
    for path in (
        "pipeline/envs/ids.py", "pipeline/envs/maze/env.py", "pipeline/envs/ogbench.py",
        "pipeline/envs/manipspace/env.py", "pipeline/envs/maze/expert.py",
        "pipeline/envs/manipspace/solver.py", "pipeline/evaluation/tasks.py",
        "pipeline/evaluation/proportions.py",
    )
}  # fmt: skip
# OGBench's puzzles join the manipulation envs (their ids, stepping, tasks and oracle); the cube
# and scene stepping, tasks and oracle are unchanged (tests/test_manipspace.py, bit for bit).
RERUN_PENDING |= {
    "pipeline/envs/ids.py": "the puzzles' ids join the manipulation ids; constants moved there "
    "before (unchanged outputs)",
    "pipeline/envs/manipspace/env.py": "puzzle envs added (button grid, neighbour toggles, tasks); "
    "cube and scene stepping unchanged; task starts built in one place (same starts)",
    "pipeline/envs/manipspace/solver.py": "the puzzles' oracle (exact Lights Out presses); the "
    "cube and scene oracle unchanged; one plan-running loop for both (same episodes)",
    "pipeline/evaluation/tasks.py": "docstrings (the puzzles' tasks); unchanged outputs",
}

# A new param at its default: the locks ran with what it now spells out (1: the paper's Gaussian).
RERUN_PENDING["train.tawm_components"] = (
    "a new key of `train` at its default (1, the paper's single Gaussian): the same runs"
)
RERUN_PENDING["train.tawm_chain"] = (
    "a new key of `train` at its default (1, the paper's one-window TAWM): the same runs"
)
RERUN_PENDING |= {
    path: "windows followed by more for a chained TAWM (train.tawm_chain, 1 by default: the same "
    "batches and updates)"
    for path in ("pipeline/training/data.py", "pipeline/training/cuda_graphs.py")
}  # fmt: skip
RERUN_PENDING["train.encoder"] = (
    "a new key of `train` at its default (gru, the paper's posterior): the same runs"
)
RERUN_PENDING["train.tawm_residual"] = (
    "a new key of `train` at its default (false, the paper's TAWM mean): the same runs"
)
RERUN_PENDING["deploy.object_subtasks"] = (
    "a new key of `deploy` at its default (false, the paper's whole-goal plans): the same runs"
)
# The mixture TAWM (`train.tawm_components`, default 1: the paper's Gaussian) joins the model,
# the rollout, the planner's networks and the validation metrics; with one component every
# computation is the one before (tests/test_tawm_mixture.py, tests/test_planning.py).
RERUN_PENDING |= {
    path: "the mixture TAWM (train.tawm_components, 1 by default), the conv posterior "
    "(train.encoder, gru by default) and the residual TAWM (train.tawm_residual, false by "
    "default): the same computations"
    for path in ("pipeline/model", "pipeline/planning", "pipeline/training/losses.py")
}  # fmt: skip
# The Adam loop of the single-step model, BC and GCBC in one place (`training/keep_best.py`): the
# same draws and updates, the same models (the main job's stages rerun bit for bit).
RERUN_PENDING |= {
    path: "the small models' Adam loop shared (training/keep_best.py): the same updates"
    for path in ("pipeline/training/keep_best.py", "pipeline/training/bc.py",
                 "pipeline/training/dynamics.py", "pipeline/value/fit.py")
}  # fmt: skip
# Views and console text only: the scene's buttons coloured by state in the recordings, the
# deploy summary's distances in success tolerances for object goals (reports unchanged).
RERUN_PENDING |= {
    path: "what a recording draws or the console prints; the reports unchanged"
    for path in ("pipeline/evaluation/report.py", "pipeline/viz/manip.py",
                 "pipeline/viz/manip_scene.py")
}  # fmt: skip

# One object of a manipulation goal at a time (`deploy.object_subtasks`, false by default: the
# whole goal, the same plans; tests/test_subtasks.py, tests/test_manip_pipeline.py).
for _path in ("pipeline/planning", "stages/deploy.py", "pipeline/envs/manipspace/env.py"):
    RERUN_PENDING[_path] += "; deploy.object_subtasks (false by default: the same plans)"
# A TAWM trained to chain skills (`train.tawm_chain`, 1 by default: eq. 16 and the same resume
# keys; tests/test_tawm_chain.py).
for _path in ("pipeline/training/losses.py", "stages/train.py"):
    RERUN_PENDING[_path] += "; train.tawm_chain (1 by default: the same updates)"

# OPOSM replans every 20 steps in params.yaml (was every skill, T = 39): the main job's seed 0
# reached 90 % of its corner-to-corner goals that way (results/stability-cpu.md). The OGBench, ant
# and manipulation params files pin the value their results ran with (their stages would rerun
# the same); the maze experiments on params.yaml itself would not.
RERUN_PENDING["stages/deploy.py"] += (
    "; deploy.replan_every at most the skills' T (the same runs: every committed one replanned "
    "within T)"
)
RERUN_PENDING["deploy.replan_every"] = (
    "params.yaml's OPOSM replans every 20 steps (was every skill, T = 39): the maze experiments' "
    "OPOSM rows (mazes, em_vi, select_deploy, mass) would change; stages on a params file that "
    "pins the old value (OGBench's mazes, the ant, manipulation) would run the same"
)


# The main job's default recipe: the conv posterior (train.encoder, was gru) and the subgoal graph
# once an episode is stuck (deploy.subgoals: enabled, was false; patience 2 and progress 0.25,
# new): corners >= 95 % on seeds 0-9 (results/stability-cpu.md, recipe default). The OGBench, ant,
# manipulation and kitchen params files and params-paper.yaml pin the values their results ran
# with (their stages would run the same); the maze experiments on params.yaml itself would not.
_MAIN_RECIPE = (
    "params.yaml's new default recipe (the conv posterior, the subgoal graph once stuck): the maze "
    "experiments' models and OPOSM rows would change; stages on a params file that pins the old "
    "value (OGBench's mazes, the ant, manipulation, the kitchen) would run the same"
)
RERUN_PENDING["train.encoder"] = _MAIN_RECIPE
for _key in ("deploy.subgoals.enabled", "deploy.subgoals.patience", "deploy.subgoals.progress"):
    RERUN_PENDING[_key] = _MAIN_RECIPE
for _path in ("pipeline/planning", "stages/deploy.py"):
    RERUN_PENDING[_path] += (
        "; the subgoal graph waits for a stuck episode with deploy.subgoals.patience (null: "
        "waypoints from the first replan, the same plans as before)"
    )

# The published numbers as data files with their sources, one package (its folder one dep entry),
# in place of the four modules pipeline/evaluation/paper*.py: the same values bit for bit; the
# reports that read them import them from there (the same pages).
RERUN_PENDING["pipeline/evaluation/published"] = (
    "(new) the published numbers as data files with their sources (tests/test_published.py): the "
    "same values, the same pages; OGBench's puzzle-3x3 / 4x4 rows there (were "
    "paper_manipulation.py's), the cube and scene rows unchanged"
)
RERUN_PENDING |= {
    path: "imports the published numbers from pipeline/evaluation/published: the same pages"
    for path in ("stages/experiments_report.py", "pipeline/reporting/ogbench_point.py")
}  # fmt: skip
for _path in ("pipeline/reporting/antmaze.py", "pipeline/reporting/manipulation.py"):
    RERUN_PENDING[_path] += "; the published numbers from pipeline/evaluation/published"

# Deploy's agents built in their own module, and its (agent, task) jobs on `deploy.workers`
# processes side by side (auto: one per job up to the cores): the same episodes, byte for byte
# (tests/test_deploy.py), in less wall-clock time.
_WORKERS = "the (agent, task) jobs on deploy.workers processes: the same reports, byte for byte"
RERUN_PENDING |= {
    "stages/deploy_agents.py": "(new) the agent builders, moved out of stages/deploy.py unchanged",
    "stages/deploy_jobs.py": f"(new) {_WORKERS}",
    "deploy.workers": f"(new) {_WORKERS}",
}
RERUN_PENDING["stages/deploy.py"] += f"; {_WORKERS}"

# The plan's uncertainty in its cost (`deploy.planner.uncertainty_weight`, 0 by default: the
# paper's cost, the same plans; tests/test_planning.py).
_UNCERTAINTY = (
    "deploy.planner.uncertainty_weight (0 by default: the same plans; the report names it)"
)
RERUN_PENDING["pipeline/planning"] += f"; {_UNCERTAINTY}"
RERUN_PENDING["deploy.planner.uncertainty_weight"] = f"(new) {_UNCERTAINTY}"

# The ant expert in one package (`pipeline/ant_expert/`: actor, config, training, check, from
# envs/, expert_config.py, training/ and evaluation/): the actor's file moved unchanged (recorded
# in the locks by `scripts/dvc_deps.py --record`); its importers changed only their imports.
RERUN_PENDING["pipeline/envs/ogbench_oracle.py"] = (
    "imports the ant expert's actor from pipeline/ant_expert/actor.py: the same code"
)
RERUN_PENDING["stages/deploy_agents.py"] += "; imports the ant expert's actor from its package"

# OGBench's manipulation envs in one package (`pipeline/envs/manipspace/`: env, data, solver, were
# manipspace.py, manipspace_data.py, manipspace_solver.py): the env's file moved unchanged
# (recorded where its lock was current); its importers changed only their imports.
RERUN_PENDING |= {
    path: "imports the manipulation envs from pipeline/envs/manipspace/: the same code"
    for path in ("pipeline/envs/batch.py", "stages/ingest.py")
}  # fmt: skip

# One route for the results pages, `oposm report <benchmark>` (were `oposm results` and
# scripts/<benchmark>_report.py): the same command lines in stages/<benchmark>_report.py, the
# commands recorded in the locks by `scripts/dvc_deps.py --record` (COMMAND_MOVES); the pages
# name the new commands.
_ROUTE = "moved from scripts/ (or stages/results.py) under `oposm report`: the same pages, which "
_ROUTE += "name the new command"
for _path in ("stages/antmaze_report.py", "stages/ogbench_point_report.py"):
    RERUN_PENDING[_path] = _ROUTE
for _path in ("stages/experiments_report.py", "stages/manipulation_report.py"):
    RERUN_PENDING[_path] += f"; {_ROUTE}"
for _path in ("pipeline/reporting/antmaze.py", "pipeline/reporting/manipulation.py",
              "pipeline/reporting/ogbench_point.py", "pipeline/evaluation/published"):  # fmt: skip
    RERUN_PENDING[_path] += "; the pages name `oposm report <benchmark>`"

# gymnasium-robotics' mazes in one folder (`pipeline/envs/maze/`: env, expert, generate, checks,
# were maze.py, expert.py, generate.py, checks.py), the MuJoCo state every env shares moved out of
# maze.py into `pipeline/envs/physics.py` (PHYSICS_SPEC, restore_physics, register_envs): the same
# code; the expert moved unchanged (recorded), the others changed only their imports.
RERUN_PENDING |= {
    path: "the maze room (pipeline/envs/maze/) and the shared MuJoCo state (pipeline/envs/"
    "physics.py, out of maze.py): the same code, moved"
    for path in ("pipeline/envs/physics.py", "pipeline/envs/maze/checks.py",
                 "pipeline/envs/maze/generate.py")
}  # fmt: skip

# The plan's support distance in its cost (`deploy.planner.support_weight`, 0 by default: the
# paper's cost, the same plans; the report names it only when it is used; tests/test_support.py).
_SUPPORT = "deploy.planner.support_weight (0 by default: the same plans and reports)"
RERUN_PENDING["pipeline/planning"] += f"; {_SUPPORT}"
RERUN_PENDING["stages/deploy_agents.py"] += f"; {_SUPPORT}"
RERUN_PENDING["deploy.planner.support_weight"] = f"(new) {_SUPPORT}"
RERUN_PENDING["deploy.planner.support_windows"] = f"(new) {_SUPPORT}: the bank's size"
RERUN_PENDING["deploy.planner.support_quantile"] = f"(new) {_SUPPORT}: its margin"
RERUN_PENDING["deploy.planner.data_skills"] = (
    "(new) deploy.planner.data_skills (0 by default: the same plans and reports)"
)

# OGBench's ant stitch and explore rows among the published numbers, and the ant page's datasets
# beyond navigate (`ogbench_name("medium-stitch")`: antmaze-medium-stitch; no paper claims there):
# the navigate mazes' reports and the other pages the same.
RERUN_PENDING["pipeline/evaluation/published"] += "; OGBench's ant stitch and explore rows"
RERUN_PENDING["pipeline/reporting/antmaze.py"] += (
    "; the stitch and explore datasets by OGBench's names, a stitch dataset's data line counts the "
    "episodes that reach their goal (the navigate mazes' reports the same)"
)
RERUN_PENDING["experiments/antmaze/notes.json"] = (
    "antmaze-medium-stitch's, antmaze-large-stitch's and antmaze-giant-stitch's notes added; the "
    "other mazes' notes the same"
)
_RESUME = "a killed deploy resumes from its finished jobs (the same episodes and reports)"
RERUN_PENDING["stages/deploy_jobs.py"] += f"; {_RESUME}"
RERUN_PENDING["stages/deploy.py"] += f"; {_RESUME}"
RERUN_PENDING["pipeline/evaluation/episode_store.py"] = f"(new) {_RESUME}"
_KEPT = "a killed ingest resumes from the episodes it generated (the same file)"
RERUN_PENDING["pipeline/sources"] += f"; {_KEPT}"
RERUN_PENDING["stages/ingest.py"] += f"; {_KEPT}"


def _covered(problem: str) -> str | None:
    """The RERUN_PENDING file a stale-lock `problem` is about, or None."""
    match = re.fullmatch(r"[^:]+: \{'(.+)': '(modified|new|deleted)'\}", problem)
    return match[1] if match and match[1] in RERUN_PENDING else None


@pytest.mark.parametrize("pipeline", PIPELINES)
def test_committed_experiments_lock_matches_params_code_and_results(pipeline):
    """A committed experiments lock records the params, code and results of its pipeline: a
    change to either without rerunning the stages it feeds fails here, unless RERUN_PENDING
    names the changed code file."""
    problems = [p for p in _stale(pipeline) if _covered(p) is None]
    assert not problems, f"{pipeline}: " + "; ".join(problems[:20])


def test_every_pending_rerun_is_still_pending():
    """RERUN_PENDING shrinks as stages rerun: each entry is what some lock is still stale for."""
    pending = {_covered(p) for pipeline in PIPELINES for p in _stale(pipeline)}
    assert set(RERUN_PENDING) <= pending, sorted(set(RERUN_PENDING) - pending)


# --- slow: the real dvc, in a temporary git copy, on tiny settings -------------------------------

TINY = {
    "ingest": "-S ingest.episodes=8 -S ingest.episode_steps=150",
    "train": "-S train.threads=1 -S train.z_dim=4 -S train.hidden=16 -S train.max_steps=20 "
    "-S train.eval_every=10 -S train.val_windows=50 -S train.checkpoint_every=10",
    "gcbc": "-S gcbc.hidden=16 -S gcbc.max_steps=50 -S gcbc.eval_every=25 "
    "-S gcbc.val_transitions=200",
    "deploy": "-S deploy.record_episodes=1 -S deploy.episodes=1 -S deploy.num_envs=1 "
    "-S deploy.max_steps=40 -S deploy.planner.horizon=2 -S deploy.planner.candidates=8 "
    "-S deploy.planner.elites=2 -S deploy.planner.iterations=2",
}


def _git(repo: Path, *args: str) -> str:
    result = subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args],
                            cwd=repo, check=True, capture_output=True, text=True)  # fmt: skip
    return result.stdout


def _dvc(repo: Path, *args: str) -> str:
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    env.pop("DVC_STAGE", None)
    result = subprocess.run([sys.executable, "-m", "dvc", *args], cwd=repo, env=env,
                            capture_output=True, text=True)  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout + result.stderr


def _tiny_repo(dest: Path, roots: list[str], runs: list[str]) -> Path:
    """A git copy of the repository whose OGBench plan holds only `roots` and `runs` (and the
    models they read), each stage on tiny settings, with no outputs and no locks."""
    files = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
                           cwd=ROOT, check=True, capture_output=True, text=True).stdout  # fmt: skip
    for name in filter(None, files.split("\0")):
        if (ROOT / name).is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, dest / name)
    for lock in ("dvc.lock", "experiments/dvc.lock", "experiments/ogbench/dvc.lock"):
        (dest / lock).unlink(missing_ok=True)  # no outputs here: only what this test runs
    plan = _plan()
    plan["runs"] = {k: plan["runs"][k] for k in runs}
    needed = {(re.search(r"deploy\.agents=\[(\w+)\]", r["deploy"])[1], r["root"])
              for r in plan["runs"].values()}  # fmt: skip
    plan["datasets"] = {k: v for k, v in plan["datasets"].items() if k in roots}
    for section, agent in (("train_on", "oposm"), ("gcbc_on", "gcbc"), ("llp_on", "llp")):
        plan[section] = {k: v for k, v in plan[section].items() if (agent, k) in needed}
    plan["set"].update(TINY)
    (dest / VARS).write_text(yaml.safe_dump(plan, sort_keys=False))
    _git(dest, "init", "-q")
    _git(dest, "add", "-A")
    _git(dest, "commit", "-qm", "copy")
    return dest


@pytest.mark.slow
def test_one_ogbench_dataset_through_dvc_repro_and_the_report(tmp_path):
    """`dataset@medium` runs one data root's whole chain (not the report); the report then
    writes results/ogbench-point.* stamped with the stage and its lock (~40 s)."""
    repo = _tiny_repo(tmp_path / "repo", ["medium"], ["medium-subgoals", "medium-gcbc"])
    first = _dvc(repo, "repro", f"{OGB}:dataset@medium")
    for stage in ("ingest@medium", "segment@medium", "train@medium", "gcbc@medium",
                  "deploy@medium-subgoals", "deploy@medium-gcbc", "dataset@medium"):  # fmt: skip
        assert f"Running stage '{OGB}:{stage}'" in first, stage
    assert f"Running stage '{OGB}:report'" not in first
    assert not list((repo / "data/experiments/ogbench/medium/models").glob("*-bc"))  # no llp
    rows = json.loads((repo / "data/experiments/ogbench/rows/medium.json").read_text())
    assert [(r["key"], r["agent"]) for r in rows] == [("medium-subgoals", "oposm"),
                                                       ("medium-gcbc", "gcbc")]  # fmt: skip
    assert rows[0]["tasks"]["ogbench"]["episodes"] == 5  # one episode on each of the five tasks
    second = _dvc(repo, "repro", OGB)
    assert re.findall(r"Running stage '([^']+)'", second) == [f"{OGB}:report"]
    text = (repo / "results/ogbench-point.md").read_text()
    assert "| medium | OPOSM + subgoals (reach 2, line of sight) |" in text
    assert "| medium | GCBC (ours) |" in text and "- medium: **" in text
    assert f"written by DVC stage `{OGB}:report`" in text and "# deploy@medium-gcbc" in text
    report = json.loads((repo / "results/ogbench-point.json").read_text())
    digest = lock_digest(repo / "experiments/ogbench/dvc.lock", exclude="report")
    assert report["stamp"]["dvc"]["upstream_sha256"] == digest
    assert report["stamp"]["commit"] and report["not_run"] == []
    assert "Data and pipelines are up to date" in _dvc(repo, "status", OGB)


@pytest.mark.slow
def test_two_queued_experiments_run_on_two_workers_and_share_the_run_cache(tmp_path):
    """docs/experiments.md's parallel recipe: one queued experiment per target, `dvc queue start
    -j 2`; then `dvc repro` of the same targets restores their outputs from the run cache the
    workers filled, running nothing (~70 s on a loaded 2-core machine)."""
    repo = _tiny_repo(tmp_path / "repo", ["medium", "large"], ["medium-gcbc", "large-gcbc"])
    targets = [f"{OGB}:ingest@medium", f"{OGB}:ingest@large"]
    for target, name in zip(targets, ("ingest-medium", "ingest-large"), strict=True):
        assert "Queued experiment" in _dvc(repo, "exp", "run", "--queue", "-n", name, target)
    try:
        assert "Started '2' new experiments task queue workers" in _dvc(
            repo, "queue", "start", "-j", "2"
        )
        deadline = time.monotonic() + 240
        while re.search(r"\b(Queued|Running)\b", status := _dvc(repo, "queue", "status")):
            assert time.monotonic() < deadline, status
            time.sleep(2)
    finally:
        _dvc(repo, "queue", "stop")
    assert re.search(r"ingest-medium\s+\S+\s+\S+\s+Success", status), status
    assert re.search(r"ingest-large\s+\S+\s+\S+\s+Success", status), status
    again = _dvc(repo, "repro", *targets)
    assert "Running stage" not in again, again
    for target in targets:
        assert f"Stage '{target}' is cached - skipping run" in again
    assert (
        repo / "data/experiments/ogbench/large/demos/ogbench-pointmaze-large-navigate.mcap"
    ).exists()


def test_the_ant_mass_sweep_names_its_mazes_dataset():
    """`figure5.name` is repeated beside `figure5.maze` (DVC cannot nest interpolations): they
    must name the same maze's dataset, or the mass stages would read another maze's models."""
    plan = yaml.safe_load((ROOT / "experiments/antmaze/params.yaml").read_text())
    fig5 = plan["figure5"]
    assert fig5["name"] == plan["mazes"][fig5["maze"]]["name"]


def test_the_ant_table3_names_its_mazes_dataset():
    """`em_vi.name` is repeated beside `em_vi.maze`, as figure 5's: the same maze's dataset."""
    plan = yaml.safe_load((ROOT / "experiments/antmaze/params.yaml").read_text())
    assert plan["em_vi"]["name"] == plan["mazes"][plan["em_vi"]["maze"]]["name"]
