"""Ant-maze data with OGBench's recipe and a real (small, random-weight) ant expert: generation,
determinism, exact physics, MCAP and `.npz` round trips, the ant checks, bad experts."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from factories import one_line_error
from typer.testing import CliRunner

from cli import app
from pipeline.ant_expert.actor import ActorSpec, DirectionActor, load_actor, save_actor
from pipeline.envs.ant import expert_observation
from pipeline.envs.batch import BatchSim
from pipeline.envs.ogbench_oracle import BFSOracle, OGBenchOracleAgent
from pipeline.envs.spec import make_env_spec
from pipeline.recording import iter_episodes, read_info, write_dataset
from pipeline.sources import open_ogbench
from pipeline.sources.ogbench import (
    check_ogbench_dataset,
    generate_ogbench,
    make_recipe,
    read_ogbench,
    write_ogbench_npz,
)

ANT = "antmaze-medium-v0"
STEPS = 40
runner = CliRunner()


def _save_actor(path, seed: int = 0, obs_dim: int = 29, robot: str = "ant") -> None:
    """A seeded random 32-unit actor whose mean head is scaled down, so that its actions stay
    small and the ant, jiggled by the recipe's noise, stays on its feet."""
    torch.manual_seed(seed)
    spec = ActorSpec(obs_dim, 8, [32], "gelu", [-1.0] * 8, [1.0] * 8, info={"robot": robot})
    actor = DirectionActor(spec)
    with torch.no_grad():
        actor.mu.weight.mul_(0.1)
        actor.mu.bias.zero_()
    save_actor(actor, path)


@pytest.fixture(scope="module")
def expert(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("expert") / "actor.safetensors"
    _save_actor(path)
    return str(path)


def _generate(expert: str, seed: int = 0, kind: str = "navigate", noise: float | None = None):
    """Two episodes of `STEPS` steps in `ANT`: (info, episodes)."""
    data = generate_ogbench(make_recipe(ANT, kind, 2, STEPS, seed, noise, expert), "ant")
    return data.info, list(data.episodes)


@pytest.fixture(scope="module")
def generated(expert):
    return _generate(expert)


def test_ant_episodes_have_the_recipes_shapes_physics_and_provenance(generated, expert) -> None:
    info, episodes = generated
    assert [len(e) for e in episodes] == [STEPS, STEPS]
    assert (info.env_id, info.state_dim, info.action_dim, info.physics_dim) == (ANT, 29, 8, 30)
    assert info.state_names[:3] == ["x", "y", "qpos[2]"] and info.goal_dim == 2
    generator = info.generator
    assert generator["noise"] == 0.2 and generator["dataset_type"] == "navigate"
    with open(expert, "rb") as f:
        assert generator["expert"]["sha256"] == hashlib.sha256(f.read()).hexdigest()
    assert generator["expert"]["info"] == {"robot": "ant"}
    assert generator["expert"]["hidden"] == [32]
    for ep in episodes:
        assert ep.observations.shape == (STEPS, 29) and ep.actions.shape == (STEPS, 8)
        assert np.abs(ep.actions).max() <= 1.0 and ep.goals.shape == (STEPS, 2)
        np.testing.assert_array_equal(ep.physics[:, 1:], ep.observations)
    np.testing.assert_allclose(np.diff(np.concatenate([e.time for e in episodes])), 0.1)
    # the recorded state is the exact physics: restore it, step the recorded action, get the next
    sim = BatchSim(make_env_spec(ANT), STEPS - 1)
    sim.set_state(episodes[0].physics[:-1])
    sim.step(episodes[0].actions[:-1])
    # (to ~1e-15: the solver's warm start is not part of MuJoCo's physics state)
    np.testing.assert_allclose(sim.observe(), episodes[0].observations[1:], rtol=0, atol=1e-9)
    report = check_ogbench_dataset(episodes, info)
    assert report.problems == [] and report.fallen_steps == 0
    assert 0.0 < report.max_step_distance < 0.3 and report.max_velocity_mismatch < 0.1


def test_without_noise_the_action_is_the_expert_walking_the_oracle_direction(expert) -> None:
    info, episodes = _generate(expert, noise=0.0)
    actor, oracle, ep = load_actor(expert), BFSOracle(ANT), episodes[0]
    for t in (0, 17, STEPS - 1):
        direction = oracle.direction(ep.observations[t, :2], ep.goals[t])
        wanted = actor.act(expert_observation(ep.observations[t], direction))
        np.testing.assert_array_equal(ep.actions[t], np.clip(wanted, -1, 1))
    assert info.generator["noise"] == 0.0


def test_the_expert_deploy_agent_acts_as_the_recipe_on_the_ant(expert) -> None:
    """`deploy.agents: [expert]` on an ant maze: noise-free, the oracle's direction walked by the
    actor (the data's actions); with noise, each episode's own stream, within the bounds."""
    _, episodes = _generate(expert, noise=0.0)
    ep = episodes[0]
    agent = OGBenchOracleAgent(ANT, noise=0.0, actor=load_actor(expert))
    agent.reset(np.stack([ep.goals[0], ep.goals[0]]), seeds=[1, 2])
    rows, states = np.array([0, 1]), ep.observations[[0, 5]]
    got = agent.act(rows, states)
    assert got.shape == (2, 8) and got.dtype == np.float64
    np.testing.assert_allclose(got[0], ep.actions[0], rtol=1e-6, atol=1e-6)
    noisy = OGBenchOracleAgent(ANT, noise=0.2, actor=load_actor(expert))
    noisy.reset(np.stack([ep.goals[0], ep.goals[0]]), seeds=[1, 2])
    a = noisy.act(rows, states[[0, 0]])
    assert not np.allclose(a[0], a[1]) and np.abs(a).max() <= 1.0  # own streams, clipped


def test_same_seed_same_data_another_seed_other_data(generated, expert) -> None:
    _, first = generated
    torch.set_num_threads(2)  # the expert runs on one thread whatever the caller's setting
    try:
        _, again = _generate(expert)
    finally:
        torch.set_num_threads(1)
    _, other = _generate(expert, seed=1)
    for a, b in zip(first, again, strict=True):
        for field in ("observations", "actions", "physics", "goals", "goal_reached", "time"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert not np.array_equal(first[0].observations, other[0].observations)


@pytest.mark.slow
def test_episodes_generated_by_worker_processes_are_the_same_data(generated, expert) -> None:
    _, first = generated
    data = generate_ogbench(
        make_recipe(ANT, "navigate", 2, STEPS, 0, None, expert), "ant", workers=2
    )
    for a, b in zip(first, list(data.episodes), strict=True):
        assert a.index == b.index
        for field in ("observations", "actions", "physics", "goals", "goal_reached", "time"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))


@pytest.mark.parametrize("kind", ["stitch", "explore"])
def test_stitch_and_explore_generate_for_the_ant(expert, kind) -> None:
    info, episodes = _generate(expert, kind=kind)
    assert info.generator["noise"] == {"stitch": 0.2, "explore": 1.0}[kind]
    assert episodes[0].observations.shape == (STEPS, 29)


def test_mcap_and_npz_round_trips_keep_the_ant_data(generated, tmp_path) -> None:
    info, episodes = generated
    write_dataset(tmp_path / "ant.mcap", info, episodes)
    assert read_info(tmp_path / "ant.mcap").generator["expert"] == info.generator["expert"]
    for a, b in zip(episodes, iter_episodes(tmp_path / "ant.mcap"), strict=True):
        for field in ("observations", "actions", "physics", "goals", "goal_reached", "time"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    npz = tmp_path / "antmaze-medium-navigate-v0.npz"
    assert write_ogbench_npz(npz, episodes, nq=15) == 2 * STEPS
    back = list(read_ogbench(npz, "back").episodes)
    np.testing.assert_allclose(back[1].physics[:, 1:], episodes[1].observations, atol=1e-5)


def _with(ep, observations):
    return dataclasses.replace(ep, observations=observations, physics=None)


def test_checks_catch_an_injected_fall_and_jump(generated) -> None:
    info, episodes = generated
    fallen = episodes[0].observations.copy()
    fallen[10:, 2] = 0.15  # torso on the floor from step 10
    report = check_ogbench_dataset([_with(episodes[0], fallen), episodes[1]], info)
    assert report.fallen_steps == STEPS - 10 and report.fallen_episodes == 1
    assert any("fallen" in p for p in report.problems)
    assert report.min_torso_height == pytest.approx(0.15)
    upside_down = episodes[0].observations.copy()
    upside_down[5:, 3:7] = [0.0, 1.0, 0.0, 0.0]  # rolled 180 degrees about x
    report = check_ogbench_dataset([_with(episodes[0], upside_down)], info, max_fallen_share=1.0)
    assert report.fallen_steps == STEPS - 5 and report.problems == []
    jumped = episodes[1].observations.copy()
    jumped[25:, 0] += 0.6  # a hidden reset 0.6 m away: within a step's reach, not its velocity's
    report = check_ogbench_dataset([episodes[0], _with(episodes[1], jumped)], info)
    assert [p for p in report.problems if "jumps" in p] == [
        f"episode 1: the ant's torso jumps {np.linalg.norm(jumped[25, :3] - jumped[24, :3]):.3f} "
        f"m at step 24 (its velocities explain all but {report.max_velocity_mismatch:.3f} m): a "
        "hidden reset or teleport?"
    ]


def test_bad_experts_and_options_are_one_line_user_errors(expert, tmp_path) -> None:
    assert "ingest.ogbench.expert" in one_line_error(lambda: make_recipe(ANT, "navigate", 1, 10, 0))
    message = one_line_error(
        lambda: make_recipe("pointmaze-medium-v0", "navigate", 1, 10, 0, None, expert)
    )
    assert "for ant mazes" in message and "null" in message

    def generate(path) -> str:
        return one_line_error(
            lambda: generate_ogbench(make_recipe(ANT, "navigate", 1, 10, 0, expert=str(path)), "a")
        )

    missing = generate(tmp_path / "nope.safetensors")
    assert "nope.safetensors not found (ingest.ogbench.expert)" in missing
    (tmp_path / "text.safetensors").write_text("not weights")
    shutil.copy(Path(expert).with_suffix(".json"), tmp_path / "text.json")
    corrupt = generate(tmp_path / "text.safetensors")
    assert corrupt.startswith("ingest.ogbench.expert: ") and "not a readable safetensors" in corrupt
    _save_actor(tmp_path / "walker.safetensors", obs_dim=27)
    assert "27 observations" in generate(tmp_path / "walker.safetensors")
    _save_actor(tmp_path / "humanoid.safetensors", robot="humanoid")
    assert "humanoid actor" in generate(tmp_path / "humanoid.safetensors")
    from pipeline.config import IngestParams

    cfg = IngestParams(source="ogbench", ogbench={"path": "x.npz", "expert": expert})
    assert "set one of them to null" in one_line_error(lambda: open_ogbench(cfg))


def test_cli_ingests_ant_data_with_the_checks_in_its_report(expert, tmp_path) -> None:
    params = {
        "ingest": {
            "name": "ant",
            "source": "ogbench",
            "episodes": 2,
            "episode_steps": 30,
            "ogbench": {"env_id": ANT, "expert": expert},
        }
    }
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    common = ["--params", str(tmp_path / "params.yaml"), "--data", str(tmp_path / "data")]
    result = runner.invoke(app, ["ingest", *common])
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "data/reports/ingest/report.json").read_text())
    assert report["steps"] == 60 and report["n_problems"] == 0
    assert report["fallen_steps"] == 0 and "max_velocity_mismatch" in report
    assert read_info(tmp_path / "data/demos/ant.mcap").generator["expert"]["info"]["robot"] == "ant"


def test_segment_exclude_fallen_drops_the_windows_of_a_fallen_ant(generated, tmp_path) -> None:
    info, (first, second) = generated
    fallen = first.observations.copy()
    fallen[25:, 3:7] = [0.0, 1.0, 0.0, 0.0]  # upside down from step 25 on
    episodes = [dataclasses.replace(first, observations=fallen)] + [
        dataclasses.replace(second, index=i, time=second.time + 10.0 * i) for i in range(1, 4)
    ]
    (tmp_path / "data/demos").mkdir(parents=True)
    write_dataset(tmp_path / "data/demos/ant.mcap", info, episodes)
    counts = {}
    for exclude in (False, True):
        params = {
            "ingest": {"name": "ant"},
            "segment": {"window": 10, "split": {"train": 0.5, "validation": 0.25, "test": 0.25},
                        "exclude_fallen": exclude},
        }  # fmt: skip
        (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
        paths = ["--params", str(tmp_path / "params.yaml"), "--data", str(tmp_path / "data")]
        result = runner.invoke(app, ["segment", *paths])
        assert result.exit_code == 0, result.output
        report = json.loads((tmp_path / "data/reports/segment/report.json").read_text())
        counts[exclude] = sum(report[f"{s}_windows"] for s in ("train", "validation", "test"))
    # Episode 0's windows starting at 16..30 hold a step from 25 on: 15 of its 31 windows.
    assert counts[False] - counts[True] == 15
