"""Random external pushes (`ingest.disturbance`): in the generated data, in the batched simulator
of validate and deploy, and recorded with the dataset."""

import dataclasses

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from cli import app
from pipeline.envs.batch import BatchSim
from pipeline.envs.disturbance import Pushes, draw_force, push_rng
from pipeline.envs.maze.checks import check_maze_dataset
from pipeline.envs.maze.expert import ExpertConfig
from pipeline.envs.maze.generate import dataset_info, generate_episodes
from pipeline.envs.spec import PointMazeSpec
from pipeline.errors import UserError

ENV_ID = "PointMaze_UMaze-v3"
MASS = 4.1887902  # the point's
PUSH = Pushes(probability=0.05, impulse=MASS * 1.0)  # 1 m/s, every 20 steps on average


def _generate(pushes: Pushes | None, seed: int = 3) -> list:
    return list(generate_episodes(ENV_ID, 2, 300, seed, ExpertConfig(), False, disturbance=pushes))


def test_pushes_change_the_velocity_by_impulse_over_mass_and_are_seeded():
    plain, pushed = _generate(None), _generate(PUSH)
    assert all(
        np.array_equal(a.observations, b.observations)
        for a, b in zip(plain, _generate(Pushes()), strict=True)
    )
    again = _generate(PUSH)
    assert all(np.array_equal(a.physics, b.physics) for a, b in zip(pushed, again, strict=True))
    first = pushed[0]
    differs = ~np.isclose(plain[0].observations, first.observations).all(axis=1)
    assert differs.any() and not differs[0]  # the same start, then a push sends it elsewhere

    # Velocity jumps beyond what the actions explain (100 N on 4.19 kg for 0.01 s: 0.24 m/s).
    jumps = np.linalg.norm(np.diff(first.observations[:, 2:], axis=0), axis=1)
    assert 5 <= np.sum(jumps > 0.5) <= 30  # ~0.05 x 299 steps


def test_one_push_adds_impulse_over_mass_to_the_velocity():
    spec = PointMazeSpec.create(ENV_ID)
    sim = BatchSim(spec, 1, pushes=Pushes(probability=1.0, impulse=MASS * 1.0))
    sim.reset(np.zeros((1, 4)))
    sim.seed_slots([0])
    assert sim.step(np.zeros((1, 2))) == {}
    assert np.hypot(*sim.observe()[0, 2:]) == pytest.approx(1.0, abs=0.02)
    assert not sim.datas[0].xfrc_applied.any()  # cleared after the step


def test_the_dataset_records_its_pushes_and_only_when_there_are_any():
    info = dataset_info(ENV_ID, "d", 0, ExpertConfig(), 2, 300, disturbance=PUSH)
    assert Pushes.of_dataset(info.generator) == PUSH
    plain = dataset_info(ENV_ID, "d", 0, ExpertConfig(), 2, 300, disturbance=Pushes())
    assert "disturbance" not in plain.generator and not Pushes.of_dataset(plain.generator).active


def test_a_slots_pushes_depend_on_its_episode_seed_not_on_the_batch():
    spec = PointMazeSpec.create(ENV_ID)
    start = np.array([0.0, 0.0, 0.0, 0.0])

    def run(seeds: list[int]) -> np.ndarray:
        sim = BatchSim(spec, len(seeds), pushes=PUSH)
        sim.reset(np.tile(start, (len(seeds), 1)))
        sim.seed_slots(seeds)
        for _ in range(100):
            assert sim.step(np.zeros((len(seeds), 2))) == {}
        return sim.observe()

    alone, together = run([7]), run([5, 7, 9])
    assert np.array_equal(alone[0], together[1])
    assert not np.allclose(together[0], together[1])  # other seeds, other pushes
    still = BatchSim(spec, 1)
    still.reset(start[None])
    still.step(np.zeros((1, 2)))
    assert np.array_equal(still.observe()[0], start)  # no pushes: at rest stays at rest
    unseeded = BatchSim(spec, 1, pushes=PUSH)
    unseeded.reset(start[None])
    with pytest.raises(RuntimeError, match="seed_slots"):
        unseeded.step(np.zeros((1, 2)))


def test_forces_are_drawn_only_when_on():
    rng = push_rng(0)
    state = rng.bit_generator.state
    assert draw_force(Pushes(), rng, 0.01) is None and rng.bit_generator.state == state
    forces = [draw_force(Pushes(1.0, 2.0), rng, 0.01) for _ in range(50)]
    assert all(np.isclose(np.hypot(*f), 200.0) for f in forces)
    with pytest.raises(UserError, match="disturbance.probability"):
        Pushes(probability=1.5)


def test_ingest_refuses_pushes_on_imported_data(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    params = {
        "ingest": {
            "name": "x",
            "source": "d4rl",
            "d4rl": {"path": "missing.hdf5"},
            "disturbance": {"probability": 0.1, "impulse": 1.0},
        }
    }
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    result = CliRunner().invoke(app, ["ingest"])
    assert result.exit_code != 0 and "ingest.disturbance" in result.output
    assert "Traceback" not in result.output


def test_the_dataset_checks_allow_one_push_of_speed_and_no_more():
    pushed = _generate(PUSH)
    info = dataset_info(ENV_ID, "d", 3, ExpertConfig(), 2, 300, disturbance=PUSH)
    plain_info = dataset_info(ENV_ID, "d", 3, ExpertConfig(), 2, 300, disturbance=Pushes())
    assert check_maze_dataset(pushed, info).problems == []

    def speed_problems(vx: float, dataset_info) -> list[str]:
        first = dataclasses.replace(pushed[0], observations=pushed[0].observations.copy())
        first.observations[100, 2] = vx  # a recorded speed on one axis (m/s)
        if first.physics is not None:
            first.physics = first.physics.copy()
            first.physics[100, 3] = vx
        report = check_maze_dataset([first, pushed[1]], dataset_info)
        return [p for p in report.problems if "speed" in p]

    # 5 m/s clip + 1 m/s slack; one push adds impulse / mass = 1 m/s.
    assert speed_problems(6.5, info) == [] and speed_problems(6.5, plain_info) != []
    assert speed_problems(7.5, info) != []
