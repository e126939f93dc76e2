"""Validation against recorded data alone (`pipeline.evaluation.recorded`, `oposm validate` on a
dataset without a simulator): hand-made predictions with known errors, a LeRobot dataset written by
`lerobot` itself through the whole CLI path, and the known answer of a simulated maze exported
with `oposm export lerobot` and re-imported as a foreign dataset."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from typer.testing import CliRunner

from cli import app
from pipeline.evaluation.open_loop import choose_starts
from pipeline.evaluation.recorded import (
    RecordedResult,
    error_table,
    headline,
    per_dim_table,
    position_dims,
    recorded_report,
)
from pipeline.segments import load_segments

runner = CliRunner()


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """Small MLPs on 2 shared cores: one intra-op thread (as tests/test_validate.py)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def _one_line_error(result) -> str:
    assert result.exit_code == 1, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    return lines[0]


# -- the metrics on hand-made predictions ---------------------------------------------------------


def test_position_dims_come_from_names():
    assert position_dims(["x", "y", "vx", "vy"]) == [0, 1]
    assert position_dims(["shoulder", "ee.pos.x", "ee.pos.y", "ee.pos.z"]) == [1, 2, 3]
    assert position_dims(["qpos_0", "Position_Y", "position_x"]) == [2, 1]
    assert position_dims(["vx", "vy", "vel_x", "vel_y", "box", "index"]) == []
    assert position_dims(["x"]) == []  # a line is not a position to draw


def _hand_made(n: int = 4, h: int = 2) -> RecordedResult:
    """Two skills of H = 2 steps from N starts, state [x, y, joint]: the recording moves x by 1
    per skill; the TAWM is 0.5 off in y at every end, the single-step model 2 off in the joint."""
    recorded = np.zeros((n, 2 * h + 1, 3))
    recorded[:, :, 0] = np.arange(2 * h + 1) / h
    tawm = recorded[:, h::h].copy()
    tawm[..., 1] += 0.5
    single = recorded.copy()
    single[..., 2] += 2.0
    std = np.full_like(tawm, 0.25)  # the y error is 2 sigma: inside 2 sigma, not inside 1
    return RecordedResult(h, np.arange(n), recorded, np.zeros((n, 2, 1)), tawm, tawm, std, single)


def test_errors_and_calibration_have_known_answers():
    names, train_std = ["x", "y", "joint"], np.array([1.0, 0.5, 4.0])
    report = recorded_report(
        _hand_made(), names, ["m", "m", "rad"], (np.zeros(3), train_std), [0, 1]
    )
    one, two = report["skills_1"], report["skills_2"]
    assert report["position_dims"] == ["x", "y"] and report["state_units"]["joint"] == "rad"
    assert (one["steps"], two["steps"]) == (2, 4)
    assert one["tawm_error_mean"] == pytest.approx(0.5)
    assert one["tawm_error_per_dim"] == pytest.approx({"x": 0, "y": 0.5, "joint": 0})
    # RMS over dims in train stds: y is 0.5 / 0.5 = 1 std off, so sqrt(1 / 3).
    assert one["tawm_norm_error_mean"] == pytest.approx(math.sqrt(1 / 3))
    assert one["single_step_error_mean"] == 0 and one["single_step_norm_error_mean"] == (
        pytest.approx(math.sqrt((2 / 4) ** 2 / 3))
    )
    assert one["no_model_error_mean"] == pytest.approx(1) and two["no_model_error_mean"] == 2
    assert one["tawm_within_1sigma_per_dim"] == {"x": 1.0, "y": 0.0, "joint": 1.0}
    assert one["tawm_within_2sigma"] == 1.0
    assert one["tawm_sigma_per_dim"]["y"] == pytest.approx(0.25)
    rows = error_table(report)
    assert [r["skills"] for r in rows] == [1, 2] and rows[1]["no_model_error"] == 2
    dims = per_dim_table(report)
    assert len(dims) == 6 and dims[2] == {
        "skills": 1,
        "dim": "joint",
        "unit": "rad",
        "tawm": 0.0,
        "single_step": 2.0,
        "no_model": 0.0,
        "tawm_sigma": 0.25,
        "tawm_within_1sigma": 1.0,
        "tawm_within_2sigma": 1.0,
    }
    top = headline(report)
    assert top["recorded_tawm_error_1"] == 0.5 and top["recorded_no_model_error_2"] == 2
    # A dim constant in the train split (std at the segments' floor) leaves the norm error.
    constant = recorded_report(
        _hand_made(), names, ["m"] * 3, (np.zeros(3), np.array([1.0, 0.5, 1e-6])), [0, 1]
    )
    assert constant["skills_1"]["single_step_norm_error_mean"] == 0
    assert constant["skills_1"]["tawm_norm_error_mean"] == pytest.approx(math.sqrt(1 / 2))
    no_pos = recorded_report(_hand_made(), names, ["m"] * 3, (np.zeros(3), train_std), [])
    assert "tawm_error_mean" not in no_pos["skills_1"] and "recorded_tawm_error_1" not in (
        headline(no_pos)
    )


def test_a_simulator_only_with_an_environment_and_physics_states(caplog):
    """Which datasets get MuJoCo rollouts beside the data-only section: those of an environment
    simulated here that recorded physics states; the others are validated on their data."""
    from factories import make_episodes, make_info

    from pipeline.segments import build_segments
    from stages.validate import simulator_for

    split = {"train": 0.5, "validation": 0.0, "test": 0.5}
    simulated = build_segments(make_episodes([30, 30]), make_info(), 5, 1, split)
    assert simulator_for(simulated).env_id == "PointMaze_Medium-v3"
    no_physics = build_segments(make_episodes([30, 30], physics_dim=0), make_info(), 5, 1, split)
    assert simulator_for(no_physics) is None and "no MuJoCo states" in caplog.text
    simulated.info.env_id = "HalfCheetah-v4"  # an environment of another suite
    assert simulator_for(simulated) is None and "no simulator for environment" in caplog.text
    simulated.info.env_id = ""  # a robot's data
    assert simulator_for(simulated) is None


# -- a LeRobot dataset written by `lerobot` itself, through the whole CLI path ---------------------

ARM_STATE = ["observation.joint pos", "observation.ee-tip"]
ARM = {
    "ingest": {
        "name": "arm",
        "source": "lerobot",
        "lerobot": {
            "repo_id": "lab/arm 3dof",
            "state_features": ARM_STATE,
            "action_feature": "cmd.vel",
        },
    },
    "segment": {"window": 11},
    "train": {"z_dim": 4, "hidden": 16, "max_steps": 20, "eval_every": 10, "val_windows": 20},
    "dynamics": {"hidden": 16, "max_steps": 40, "eval_every": 20},
    "validate": {"starts": 20, "skills": 3, "particles": 8, "record_starts": 2},
}


def _arm_episode(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    """A planar 3-joint arm (links 0.3, 0.25, 0.1 m) under joint-velocity commands held for 10
    steps (its "skills") at 30 fps; the state is the joints and the tip position."""
    cmd = np.repeat(rng.uniform(-1, 1, size=(-(-n // 10), 3)), 10, axis=0)[:n]
    q = np.cumsum(np.vstack([rng.uniform(-1, 1, (1, 3)), cmd[:-1] / 30]), axis=0)
    angles = np.cumsum(q, axis=1)
    links = np.array([0.3, 0.25, 0.1])
    tip = np.stack(
        [(links * np.cos(angles)).sum(1), (links * np.sin(angles)).sum(1), np.full(n, 0.05)], 1
    )
    return {"q": q.astype(np.float32), "tip": tip.astype(np.float32), "cmd": cmd.astype(np.float32)}


@pytest.fixture(scope="module")
def arm_dir(tmp_path_factory) -> Path:
    """4 episodes of 70 frames, written with LeRobot's own writer; features with odd names."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = tmp_path_factory.mktemp("arm") / "lerobot"
    vec = lambda n, names: {"dtype": "float32", "shape": (n,), "names": names}  # noqa: E731
    features = {
        "observation.joint pos": vec(3, ["shoulder pan", "elbow/flex", "wrist.roll"]),
        "observation.ee-tip": vec(3, ["x", "y", "z"]),
        "cmd.vel": vec(3, ["d shoulder", "d elbow", "d wrist"]),
    }
    ds = LeRobotDataset.create(
        "lab/arm 3dof", fps=30, features=features, root=root, use_videos=False, video_backend="pyav"
    )
    rng = np.random.default_rng(0)
    for _ in range(4):
        ep = _arm_episode(rng, 70)
        for t in range(70):
            ds.add_frame(
                {
                    "observation.joint pos": ep["q"][t],
                    "observation.ee-tip": ep["tip"][t],
                    "cmd.vel": ep["cmd"][t],
                    "task": "reach",
                }
            )
        ds.save_episode()
    ds.finalize()
    return root


@pytest.fixture(scope="module")
def arm_run(arm_dir, tmp_path_factory):
    """ingest, segment, train, dynamics and validate of the arm, no simulator anywhere."""
    work = tmp_path_factory.mktemp("arm-run")
    params = {
        **ARM,
        "ingest": {**ARM["ingest"], "lerobot": {**ARM["ingest"]["lerobot"], "root": str(arm_dir)}},
    }
    (work / "params.yaml").write_text(yaml.safe_dump(params))
    common = [
        "--params",
        str(work / "params.yaml"),
        "--data",
        str(work / "data"),
        "--metrics",
        str(work / "metrics"),
    ]
    for command in ("ingest", "segment", "train", "dynamics", "validate"):
        result = runner.invoke(app, [command, *common])
        assert result.exit_code == 0, (command, result.output)
    return work, common


def test_robot_dataset_validates_against_its_recorded_data(arm_run):
    work, common = arm_run
    data = work / "data"
    report = json.loads((data / "reports/validate/report.json").read_text())
    assert report["simulated"] is False and "prior" not in report
    section = report["recorded"]
    assert section["skill_horizon"] == 10 and section["starts"] == 20
    assert section["position_dims"] == ["x", "y", "z"]
    names = ["shoulder pan", "elbow/flex", "wrist.roll", "x", "y", "z"]
    assert list(section["state_units"]) == names
    assert list(k for k in section if k.startswith("skills_")) == [
        "skills_1",
        "skills_2",
        "skills_3",
    ]
    # No model's error is the recorded motion itself, in the dataset's units: recomputed here from
    # the segments (the starts are validate's: the same seeded draw).
    segments = load_segments(data / "segments/arm")
    starts = choose_starts(segments, 20, 30, 0)
    for k in (1, 3):
        moved = np.abs(segments.states[starts + 10 * k] - segments.states[starts]).mean(0)
        m = section[f"skills_{k}"]
        got = [m["no_model_error_per_dim"][n] for n in names]
        np.testing.assert_allclose(got, moved, rtol=1e-6)
        tip = np.linalg.norm(
            segments.states[starts + 10 * k, 3:] - segments.states[starts, 3:], axis=1
        )
        assert m["no_model_error_mean"] == pytest.approx(tip.mean(), rel=1e-6)
        for key in (
            "tawm_norm_error_mean",
            "single_step_norm_error_mean",
            "tawm_nll",
            "tawm_error_median",
        ):
            assert math.isfinite(m[key]), key
        assert 0 <= m["tawm_within_1sigma"] <= m["tawm_within_2sigma"] <= 1
    metrics = json.loads((work / "metrics/validate.json").read_text())
    assert {
        "recorded_tawm_norm_error_1",
        "recorded_single_step_error_3",
        "recorded_tawm_within_1sigma_1",
    } <= set(metrics)
    assert metrics["recorded_no_model_error_3"] == round(
        section["skills_3"]["no_model_error_mean"], 4
    )
    rows = (data / "reports/validate/recorded_error_vs_horizon.csv").read_text().splitlines()
    assert rows[0].startswith("skills,steps,tawm_norm_error,") and len(rows) == 4
    dims = (data / "reports/validate/recorded_error_per_dim.csv").read_text().splitlines()
    assert len(dims) == 1 + 3 * 6 and dims[2].startswith("1,elbow/flex,,")
    assert not (data / "reports/validate/end_positions.csv").exists()

    from rerun.chunk import RrdReader

    entities = set(
        RrdReader(data / "recordings/validate.rrd").stream().collect().schema().entity_paths()
    )
    for path in (
        "/recorded/start_0/dim_0/recorded",
        "/recorded/start_1/dim_5/tawm_high",
        "/recorded/start_0/dim_2/single_step",
        "/recorded/start_0/positions/tawm/ends",
    ):
        assert path in entities, sorted(entities)[:20]
    # Rerun with the same inputs: byte-identical report, CSVs and metrics (no seconds in them).
    before = {
        p: p.read_bytes()
        for p in [*(data / "reports/validate").iterdir(), work / "metrics/validate.json"]
    }
    again = runner.invoke(app, ["validate", *common])
    assert again.exit_code == 0, again.output
    assert {p: p.read_bytes() for p in before} == before


def test_robot_dataset_views_exports_and_deploy_refuses_in_one_line(arm_run, tmp_path):
    """The rest of a robot user's path: view the run and the dataset, export the dataset; deploy
    needs a simulator and says so in one line."""
    work, common = arm_run
    data = work / "data"
    shown = runner.invoke(app, ["view", "--dry-run", "--data", str(data)])
    assert shown.exit_code == 0 and str(data / "recordings/validate.rrd") in shown.output
    shown = runner.invoke(app, ["view", "--dry-run", str(data / "demos/arm.mcap")])
    assert shown.exit_code == 0, shown.output
    exported = runner.invoke(
        app, ["export", "lerobot", str(data / "demos/arm.mcap"), str(tmp_path / "again")]
    )
    assert exported.exit_code == 0, exported.output
    assert "4 episodes, 280 frames at 30 fps" in exported.output
    line = _one_line_error(runner.invoke(app, ["deploy", *common]))
    assert "no simulator for environment ''" in line


def test_robot_model_of_another_dataset_is_a_one_line_error(arm_run, tmp_path):
    work, _ = arm_run
    data = tmp_path / "data"
    shutil.copytree(work / "data/segments", data / "segments")
    shutil.copytree(work / "data/models", data / "models")
    config = data / "models/arm/config.json"
    meta = json.loads(config.read_text())
    meta["info"]["state_names"] = ["a", "b", "c", "x", "y", "z"]
    config.write_text(json.dumps(meta))
    result = runner.invoke(
        app,
        [
            "validate",
            "--params",
            str(work / "params.yaml"),
            "--data",
            str(data),
            "--metrics",
            str(tmp_path / "m"),
        ],
    )
    assert "state_names" in _one_line_error(result)
    (data / "segments/arm/segments.safetensors").write_bytes(b"not safetensors")
    result = runner.invoke(
        app,
        [
            "validate",
            "--params",
            str(work / "params.yaml"),
            "--data",
            str(data),
            "--metrics",
            str(tmp_path / "m"),
        ],
    )
    assert "segments.safetensors is unreadable" in _one_line_error(result)


# -- the known answer: a simulated maze, exported and re-imported as a foreign dataset -------------

MAZE = {
    "ingest": {"name": "maze", "episodes": 6, "episode_steps": 150, "seed": 3},
    "segment": {"window": 20},
    "train": {"z_dim": 4, "hidden": 32, "max_steps": 40, "eval_every": 20, "val_windows": 50},
    "dynamics": {"hidden": 32, "max_steps": 100, "eval_every": 50},
    "validate": {"starts": 6, "skills": 2, "repeats": 2, "particles": 8, "record_starts": 1},
}
STAGES = ("segment", "train", "dynamics", "validate")


def _run(work: Path, params: dict, commands) -> list[str]:
    work.mkdir(exist_ok=True)
    (work / "params.yaml").write_text(yaml.safe_dump(params))
    common = ["--params", str(work / "params.yaml"), "--data", str(work / "data")]
    common += ["--metrics", str(work / "metrics")]
    for command in commands:
        result = runner.invoke(app, [command, *common])
        assert result.exit_code == 0, (command, result.output)
    return common


def test_foreign_reimport_of_a_simulated_maze_agrees_with_the_simulators_validation(tmp_path):
    """The maze's data through `oposm export lerobot`, its `meta/oposm.json` removed: a LeRobot
    dataset like any robot's (no environment, no physics). Trained with the same params, the
    models are the same, and validate draws the same held-out windows, so the data-only errors
    after k recorded skills are the simulator run's posterior rows against the recording.

    Tolerance: the TAWM starts from the recorded s_0 in both (the simulator run's chain starts at
    the restored state, equal to the float32 recording to 1e-6), so its chained means agree to
    float32 round-off: rel 1e-5. No model's s_0 is the simulator's float64 observation there and
    the float32 recording here: rel 1e-6 on distances of metres.
    """
    sim = tmp_path / "sim"
    _run(sim, MAZE, ("ingest", *STAGES))
    exported = runner.invoke(
        app, ["export", "lerobot", str(sim / "data/demos/maze.mcap"), str(tmp_path / "lr")]
    )
    assert exported.exit_code == 0, exported.output
    (tmp_path / "lr/meta/oposm.json").unlink()
    ingest = {"name": "maze", "source": "lerobot", "lerobot": {"root": str(tmp_path / "lr")}}
    foreign = tmp_path / "foreign"
    _run(foreign, {**MAZE, "ingest": ingest}, ("ingest", *STAGES))

    simulated = json.loads((sim / "data/reports/validate/report.json").read_text())
    recorded = json.loads((foreign / "data/reports/validate/report.json").read_text())
    assert simulated["simulated"] and not recorded["simulated"]
    assert recorded["recorded"]["position_dims"] == ["x", "y"]  # named by the export
    assert recorded["recorded"]["state_units"] == {"x": "", "y": "", "vx": "", "vy": ""}
    for k in ("skills_1", "skills_2"):
        posterior, data_only = simulated["posterior"][k], recorded["recorded"][k]
        assert data_only["steps"] == posterior["steps"]
        for which in ("mean", "median"):
            assert data_only[f"tawm_error_{which}"] == pytest.approx(
                posterior[f"tawm_recorded_error_{which}"], rel=1e-5
            )
            assert data_only[f"no_model_error_{which}"] == pytest.approx(
                posterior[f"no_model_recorded_error_{which}"], rel=1e-6
            )
        # ... and the simulator run's own data-only section is the same as the foreign one's.
        assert simulated["recorded"][k]["tawm_norm_error_mean"] == pytest.approx(
            data_only["tawm_norm_error_mean"], rel=1e-5
        )
    # With a simulator nothing was removed: its rollouts, CSVs and headline keys stay.
    assert {"prior", "posterior", "real_wall_crossing"} <= set(simulated)
    headline_sim = json.loads((sim / "metrics/validate.json").read_text())
    assert {"tawm_error_1", "single_step_error_2", "recorded_tawm_error_1"} <= set(headline_sim)
    assert (sim / "data/reports/validate/end_positions.csv").exists()
    assert (sim / "data/reports/validate/recorded_error_vs_horizon.csv").exists()
