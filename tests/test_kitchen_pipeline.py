"""The Franka kitchen through the pipeline: D4RL's score by the env's own rule, the kitchen's
task, the refusals, and a tiny end to end run (a Minari kitchen dataset of random actions made
here with `write_kitchen_minari` -> ingest -> segment -> train / dynamics / bc / gcbc ->
validate -> deploy on the kitchen-mixed task set for the env's 280 steps; no download)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from factories import one_line_error

from pipeline.config import load_params
from pipeline.envs.batch import BatchSim
from pipeline.envs.kitchen import (
    EPISODE_STEPS,
    KETTLE_POSITION_DIMS,
    KITCHEN_TASK_SETS,
    OBS_ELEMENT_GOALS,
    OBS_ELEMENT_INDICES,
    KitchenSpec,
    dataset_task_set,
    kitchen_spec,
    make_kitchen_env,
    write_kitchen_minari,
)
from pipeline.envs.spec import make_env_spec
from pipeline.evaluation.episodes import RunConfig, run_episodes
from pipeline.evaluation.goals import GoalRule
from pipeline.evaluation.tasks import check_kitchen_tasks, kitchen_episodes
from pipeline.paths import Paths
from pipeline.recording import read_info

ROOT = Path(__file__).resolve().parents[1]
MIXED = list(KITCHEN_TASK_SETS["kitchen-mixed"])


@pytest.fixture(scope="module")
def mixed() -> KitchenSpec:
    return kitchen_spec({"tasks_to_complete": MIXED})


class StandStill:
    """Zero joint velocities: the arm holds its pose."""

    name = "still"

    def reset(self, goals, seeds) -> None:
        pass

    def act(self, rows, states) -> np.ndarray:
        return np.zeros((len(rows), 9))


# --- tasks and the score -----------------------------------------------------------------------


def test_make_env_spec_builds_the_kitchen_of_the_datasets_subtasks(mixed):
    spec = make_env_spec("FrankaKitchen-v1", {"tasks_to_complete": MIXED})
    assert spec is mixed and spec.subtasks == tuple(
        sorted(MIXED, key=list(OBS_ELEMENT_INDICES).index)
    )
    assert (spec.state_dim, spec.action_dim, spec.physics_dim) == (59, 9, 89)
    assert spec.max_episode_steps == EPISODE_STEPS == 280


@pytest.mark.filterwarnings("ignore:.*share an object")
def test_one_subtask_at_its_goal_scores_a_quarter_by_the_envs_rule(mixed):
    """The microwave door put at its goal in the start state: after three still steps our
    evaluation has the microwave complete at step 1 and D4RL's score 1/4, as the noise-free env
    counts it (`episode_task_completions`)."""
    (episode,) = kitchen_episodes(mixed, ["kitchen"], 1, seed=0)["kitchen-mixed"]
    physics = episode.physics.copy()
    physics[1 + OBS_ELEMENT_INDICES["microwave"][0]] = OBS_ELEMENT_GOALS["microwave"][0]
    start = type(episode)(episode.task, 0, episode.start, episode.goal, episode.seed, physics)
    (result,), _ = run_episodes(StandStill(), BatchSim(mixed, 1), [start], RunConfig(3, None))
    assert result.steps == 3 and not result.success and result.error is None
    assert result.subtasks_done == [None, None, 1, None]  # bottom burner, light switch, microwave
    assert result.score == 0.25 and result.to_json()["score"] == 0.25

    env = make_kitchen_env(tasks_to_complete=MIXED, robot_noise_ratio=0.0, object_noise_ratio=0.0)
    try:
        env.reset(seed=0)
        mixed.set_physics_state(env.unwrapped.data, physics, env.unwrapped.model)
        for _ in range(3):
            *_, info = env.step(np.zeros(9))
        assert info["episode_task_completions"] == ["microwave"]
        assert len(info["episode_task_completions"]) / len(MIXED) == result.score
    finally:
        env.close()


def test_every_subtask_once_is_success_and_ends_the_episode(mixed):
    """All four elements at their goals: success at the first step, D4RL's score 1."""
    (episode,) = kitchen_episodes(mixed, ["kitchen"], 1, seed=0)["kitchen-mixed"]
    physics = episode.physics.copy()
    for task in MIXED:
        physics[[1 + i for i in OBS_ELEMENT_INDICES[task]]] = OBS_ELEMENT_GOALS[task]
    start = type(episode)(episode.task, 0, episode.start, episode.goal, episode.seed, physics)
    (result,), _ = run_episodes(StandStill(), BatchSim(mixed, 1), [start], RunConfig(5, None))
    assert result.success and result.steps_to_goal == 1 and result.steps == 1
    assert result.score == 1.0 and GoalRule.of_spec(mixed).subtasks is not None


def test_kitchen_tasks_and_their_refusals(mixed):
    episodes = kitchen_episodes(mixed, ["kitchen"], 2, seed=0, task_set="kitchen-mixed")
    assert list(episodes) == ["kitchen-mixed"] and len(episodes["kitchen-mixed"]) == 2
    a, b = episodes["kitchen-mixed"]
    assert np.array_equal(a.physics, b.physics) and a.seed != b.seed  # the reset is deterministic
    assert np.allclose(a.goal, np.concatenate([OBS_ELEMENT_GOALS[t] for t in mixed.subtasks]))
    assert "deploy.tasks=[kitchen]" in one_line_error(
        lambda: check_kitchen_tasks("FrankaKitchen-v1", ["kitchen", "corners"])
    )
    custom = kitchen_spec({"tasks_to_complete": ["microwave", "kettle"]})
    assert "no known task set" in one_line_error(
        lambda: kitchen_episodes(custom, ["kitchen"], 1, seed=0)
    )
    partial = ["microwave", "kettle", "light switch", "slide cabinet"]
    assert dataset_task_set(partial, "D4RL/kitchen/complete-v2") == "kitchen-complete"
    assert dataset_task_set(partial, "D4RL/kitchen/partial-v2") == "kitchen-partial"
    assert dataset_task_set(MIXED, "D4RL/kitchen/mixed-v2") == "kitchen-mixed"


def test_a_kitchen_dataset_of_an_unknown_task_set_is_refused_in_one_line(tmp_path):
    from stages import ingest

    folder = write_kitchen_minari(
        tmp_path / "minari", episode_steps=(3,), tasks_to_complete=["microwave", "kettle"]
    )
    params = load_params(
        ROOT / "params.yaml", ["ingest.source=minari", f"ingest.minari.path={folder}"]
    )
    message = one_line_error(lambda: ingest.run(params, Paths(tmp_path / "data"), progress=False))
    assert "['microwave', 'kettle'] are no known task set" in message
    assert "kitchen-mixed" in message


# --- end to end --------------------------------------------------------------------------------

TRAINED = ("train", "dynamics", "bc", "gcbc")

TINY = [
    "ingest.name=kitchen",
    "ingest.source=minari",
    "segment.window=5",
    "segment.split.train=0.34",
    "segment.split.validation=0.33",
    "segment.split.test=0.33",
    *(f"{s}.{k}" for s in TRAINED for k in ("max_steps=3", "eval_every=3")),
    *(f"{s}.{k}" for s in TRAINED for k in ("hidden=16", "batch_size=8")),
    "train.z_dim=4",
    "train.val_windows=8",
    "train.checkpoint_every=3",
    "train.threads=1",
    *(f"{s}.val_transitions=8" for s in ("dynamics", "bc", "gcbc")),
    "validate.starts=2",
    "validate.skills=2",
    "validate.repeats=1",
    "validate.particles=4",
    "validate.record_starts=1",
    "deploy.tasks=[kitchen]",
    "deploy.agents=[oposm,llp,gcbc]",
    "deploy.subgoals.enabled=false",  # the subgoal graph is a maze's (params-kitchen-mixed.yaml)
    "deploy.episodes=1",
    "deploy.planner.horizon=2",
    "deploy.planner.candidates=8",
    "deploy.planner.elites=2",
    "deploy.planner.iterations=2",
    "deploy.llp.horizon=4",
    "deploy.llp.execute=4",
    "deploy.llp.candidates=8",
    "deploy.llp.elites=2",
    "deploy.llp.iterations=2",
    "deploy.record_episodes=1",
]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """Every stage on a Minari kitchen-mixed dataset of 3 episodes of random actions (30, 20 and
    25 steps), models trained 3 steps; OPOSM, LLP and GCBC deployed on one episode."""
    from stages import bc, deploy, dynamics, gcbc, ingest, segment, train, validate

    root = tmp_path_factory.mktemp("kitchen")
    folder = write_kitchen_minari(
        root / "minari", "oposm/kitchen-mixed-random-v0", (30, 20, 25), tasks_to_complete=MIXED
    )
    overrides = [*TINY, f"ingest.minari.path={folder}"]
    params = load_params(ROOT / "params.yaml", overrides)
    paths = Paths(root / "data")
    ingested = ingest.run(params, paths, progress=False)
    for stage in (segment, train, dynamics, bc, gcbc, validate):
        stage.run(params, paths)
    report = deploy.run(params, paths, progress=False)
    return overrides, paths, ingested, report


@pytest.mark.slow
def test_the_kitchen_runs_end_to_end(tiny_run, mixed):
    overrides, paths, ingested, report = tiny_run
    info = read_info(paths.demos("kitchen"))
    assert (info.env_id, info.state_dim, info.action_dim, info.physics_dim) == (
        "FrankaKitchen-v1",
        59,
        9,
        89,
    )
    assert info.env_kwargs["tasks_to_complete"] == list(mixed.subtasks) and info.goal_dim == 12
    assert info.generator["kitchen_task_set"] == "kitchen-mixed" and info.control_period == 0.08
    assert info.state_names[0] == "robot:panda0_joint1" and info.state_names[-1] == "kettle_wz"
    assert [info.state_names[d] for d in KETTLE_POSITION_DIMS] == [
        "kettle_x",
        "kettle_y",
        "kettle_z",
    ]
    assert ingested["steps"] == 75 and ingested["episodes"] == 3

    validated = json.loads((paths.root / "reports/validate/report.json").read_text())
    assert validated["simulated"] is True and validated["position_unit"] == "observation units"
    numbers = [v for v in _leaves(validated["prior"]) if isinstance(v, float)]
    assert numbers and all(np.isfinite(numbers))
    assert (paths.root / "recordings/validate.rrd").stat().st_size > 0

    assert report["env_id"] == "FrankaKitchen-v1" and report["tasks"] == ["kitchen-mixed"]
    assert report["max_steps"] == 280 and report["distance_unit"] == "success tolerances"
    rows = json.loads((paths.root / "reports/deploy/episodes.json").read_text())
    assert sorted(r["agent"] for r in rows) == ["gcbc", "llp", "oposm"]
    (start,) = kitchen_episodes(mixed, ["kitchen"], 1, 0)["kitchen-mixed"]
    for r in rows:
        assert r["task"] == "kitchen-mixed" and r["error"] is None
        assert r["steps"] == 280 or r["success"]
        assert np.array_equal(r["start"], start.start) and np.allclose(r["goal"], start.goal)
        assert (
            len(r["subtasks_done"]) == 4
            and r["score"] == sum(s is not None for s in r["subtasks_done"]) / 4
        )
    for agent in ("oposm", "llp", "gcbc"):
        section = report["by_agent"][agent]["kitchen-mixed"]
        assert section["episodes"] == 1 and 0.0 <= section["score_mean"] <= 1.0
    assert report["by_agent"]["oposm"]["replan_every"] == 4  # tau = window - 1
    recordings = sorted(p.name for p in (paths.root / "recordings/deploy").iterdir())
    assert recordings == [
        "gcbc-kitchen-mixed-0000.rrd",
        "llp-kitchen-mixed-0000.rrd",
        "oposm-kitchen-mixed-0000.rrd",
        "overview.rrd",
    ]
    assert all((paths.root / "recordings/deploy" / n).stat().st_size > 0 for n in recordings)


@pytest.mark.slow
def test_deploy_refuses_what_the_kitchen_cannot_do(tiny_run):
    from stages import deploy

    overrides, paths, _, _ = tiny_run
    cases = {
        "deploy.tasks=[corners]": "deploy.tasks=[kitchen]",
        "deploy.subgoals.enabled=true": "subgoal graph",
        "deploy.agents=[expert]": "no expert agent",
    }
    for override, expected in cases.items():
        changed = load_params(ROOT / "params.yaml", [*overrides, override])
        assert expected in one_line_error(lambda p=changed: deploy.run(p, paths, progress=False))


def _leaves(tree):
    if isinstance(tree, dict):
        for value in tree.values():
            yield from _leaves(value)
    elif isinstance(tree, list):
        for value in tree:
            yield from _leaves(value)
    else:
        yield tree
