"""Importers (LeRobot, D4RL, Minari) and LeRobot export, on datasets the real libraries write.

Each source's dataset is made in tmp_path by that source's own writer (LeRobot's
`LeRobotDataset.create` / `add_frame` / `save_episode` / `finalize`, Minari's `DataCollector`, h5py
in D4RL's layout), imported, and compared frame by frame with what was written. The CLI tests
then run `oposm ingest` and an unchanged `oposm segment` on each import.
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from cli import app
from pipeline.envs.maze.env import cell_to_xy, free_cells, make_maze_env, maze_layout, maze_of
from pipeline.envs.maze.expert import ExpertConfig
from pipeline.envs.maze.generate import dataset_info, generate_episodes
from pipeline.envs.physics import register_envs
from pipeline.errors import UserError
from pipeline.recording import read_episodes, read_info, write_dataset
from pipeline.sources import export_lerobot, read_d4rl, read_lerobot, read_minari
from pipeline.sources.maze2d import Maze2dMap

ENV_ID = "PointMaze_UMaze-v3"
DT = 0.01
F32 = 1e-6  # float32 round-off on values of a few metres
runner = CliRunner()


# --- datasets written by the real libraries ------------------------------------------------------


@pytest.fixture(scope="module")
def expert(tmp_path_factory) -> Path:
    """Our own MCAP dataset: the built-in expert in UMaze, 4 episodes x 120 steps."""
    path = tmp_path_factory.mktemp("expert") / "expert.mcap"
    info = dataset_info(ENV_ID, "expert", 3, ExpertConfig(), 4, 120)
    write_dataset(path, info, generate_episodes(ENV_ID, 4, 120, 3, ExpertConfig(), False))
    return path


@pytest.fixture(scope="module")
def lerobot_arm(tmp_path_factory) -> tuple[Path, list[dict[str, np.ndarray]]]:
    """A LeRobot v3.0 dataset (3 episodes of 7, 12, 9 frames at 30 fps, with a camera)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = tmp_path_factory.mktemp("lerobot") / "arm"
    vec = lambda n, names=None: {"dtype": "float32", "shape": (n,), "names": names}  # noqa: E731
    features = {
        "observation.state": vec(3, ["shoulder", "elbow", "wrist"]),
        "observation.environment_state": vec(2),
        "observation.images.cam": {"dtype": "image", "shape": (4, 4, 3), "names": None},
        "action": vec(2, ["u", "v"]),
        "next.reward": vec(1),
    }
    ds = LeRobotDataset.create(
        "test/arm", fps=30, features=features, root=root, use_videos=False, video_backend="pyav"
    )
    rng, written = np.random.default_rng(0), []
    for n, task in ((7, "pick"), (12, "place"), (9, "pick")):
        frames = [
            {
                "observation.state": rng.normal(size=3).astype(np.float32),
                "observation.environment_state": rng.normal(size=2).astype(np.float32),
                "observation.images.cam": rng.integers(0, 255, (4, 4, 3), dtype=np.uint8),
                "action": rng.uniform(-1, 1, 2).astype(np.float32),
                "next.reward": np.array([t], dtype=np.float32),
            }
            for t in range(n)
        ]
        for frame in frames:
            ds.add_frame({**frame, "task": task})
        ds.save_episode()
        written.append({k: np.stack([f[k] for f in frames]) for k in frames[0]})
    ds.finalize()
    return root, written


def _d4rl_coords(xy: np.ndarray, layout: dict) -> np.ndarray:
    """gymnasium-robotics positions -> D4RL maze2d qpos, from the two mazes' cell definitions.

    gymnasium: cell (row, col) spans x in [col, col + 1] - x_center, y in y_center - [row + 1, row].
    D4RL: qpos (i - 0.2, j - 0.2) is the centre of cell (i, j) (ball body at 1.2, walls at +1).
    """
    row = layout["y_map_center"] - xy[:, 1] - 0.5
    col = xy[:, 0] + layout["x_map_center"] - 0.5
    return np.column_stack([row, col]) - 0.2


@pytest.fixture(scope="module")
def d4rl_file(tmp_path_factory, expert) -> tuple[Path, list]:
    """The expert's data as a D4RL maze2d file, cut into episodes of 200, 160 and 120 steps: the
    first ends at a terminal, the others at timeouts."""
    env = make_maze_env(ENV_ID)
    layout = maze_layout(env)
    env.close()
    eps = read_episodes(expert)
    cat = {k: np.concatenate([getattr(e, k) for e in eps]) for k in ("observations", "actions")}
    cat["goals"] = np.concatenate([e.goals for e in eps])
    obs, act = cat["observations"], cat["actions"]
    qpos = _d4rl_coords(obs[:, :2], layout)
    qvel = np.column_stack([-obs[:, 3], obs[:, 2]])  # D4RL axis 0 runs down the rows (-y)
    ends, n = [200, 360, 480], len(obs)
    terminals, timeouts = np.zeros(n, bool), np.zeros(n, bool)
    terminals[199], timeouts[359], timeouts[479] = True, True, True
    rewards = np.random.default_rng(1).random(n).astype(np.float32)
    path = tmp_path_factory.mktemp("d4rl") / "maze2d-umaze-test.hdf5"
    with h5py.File(path, "w") as f:
        f["observations"] = np.column_stack([qpos, qvel]).astype(np.float32)
        f["actions"] = np.column_stack([-act[:, 1], act[:, 0]]).astype(np.float32)
        f["rewards"], f["terminals"], f["timeouts"] = rewards, terminals, timeouts
        f["infos/goal"] = _d4rl_coords(cat["goals"], layout).astype(np.float32)
        f["infos/qpos"], f["infos/qvel"] = qpos.astype(np.float32), qvel.astype(np.float32)
    cuts = np.split(np.arange(n), ends[:-1])
    return path, [{k: v[idx] for k, v in {**cat, "rewards": rewards}.items()} for idx in cuts]


@pytest.fixture(scope="module")
def minari_dir(tmp_path_factory) -> tuple[Path, list[dict[str, np.ndarray]]]:
    """A Minari PointMaze dataset recorded with `DataCollector`: 3 episodes of random actions
    (40 steps cut by the time limit, then 33 and 27 steps cut by a reset)."""
    import gymnasium as gym
    import minari

    register_envs()
    root = tmp_path_factory.mktemp("minari")
    rng, written = np.random.default_rng(2), []
    with pytest.MonkeyPatch.context() as mp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Minari's advice to set author, code link, eval env
        mp.setenv("MINARI_DATASETS_PATH", str(root))
        env = minari.DataCollector(
            gym.make(ENV_ID, max_episode_steps=40, continuing_task=True), record_infos=True
        )
        for seed, n in ((0, 40), (1, 33), (2, 27)):
            obs, _ = env.reset(seed=seed)
            rec = {"obs": [obs["observation"]], "goal": [obs["desired_goal"]], "act": []}
            for _ in range(n):
                action = rng.uniform(-1, 1, 2).astype(np.float32)
                obs, *_ = env.step(action)
                rec["obs"].append(obs["observation"])
                rec["goal"].append(obs["desired_goal"])
                rec["act"].append(action)
            written.append({k: np.array(v[:n]) for k, v in rec.items()})
        env.create_dataset("test/umaze-v0", algorithm_name="random", description="test")
        env.close()
    return root / "test" / "umaze-v0", written


# --- LeRobot -------------------------------------------------------------------------------------


def test_lerobot_import_matches_frame_by_frame(lerobot_arm, caplog):
    root, written = lerobot_arm
    state = ["observation.state", "observation.environment_state"]
    with caplog.at_level(logging.WARNING):
        imported = read_lerobot("test/arm", "arm", root=root, state_features=state)
        episodes = list(imported.episodes)
    assert "observation.images.cam" in caplog.text  # skipped with a notice, never silently
    info = imported.info
    assert info.source == "lerobot" and info.control_period == pytest.approx(1 / 30)
    assert info.state_names[:3] == ["shoulder", "elbow", "wrist"]
    assert info.state_names[3:] == [
        "observation.environment_state[0]",
        "observation.environment_state[1]",
    ]
    assert info.action_names == ["u", "v"]
    assert info.generator["tasks"] == ["pick", "place"]
    assert info.generator["episode_tasks"] == [[0], [1], [0]]
    start = 0
    for ep, ref in zip(episodes, written, strict=True):
        n = len(ref["action"])
        expected = np.concatenate([ref[k] for k in state], axis=1).astype(np.float64)
        np.testing.assert_array_equal(ep.observations, expected)
        np.testing.assert_array_equal(ep.actions, ref["action"].astype(np.float64))
        np.testing.assert_array_equal(ep.rewards, np.arange(n))
        np.testing.assert_allclose(ep.time, (start + np.arange(n)) / 30, rtol=0, atol=1e-12)
        start += n


def test_lerobot_export_round_trip(expert, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    summary = export_lerobot(expert, tmp_path / "lr")
    assert (summary.episodes, summary.frames, summary.fps) == (4, 480, 100)
    opened = LeRobotDataset(summary.repo_id, root=tmp_path / "lr", video_backend="pyav")
    assert opened.meta.info.codebase_version == "v3.0" and len(opened) == 480
    imported = read_lerobot(summary.repo_id, "back", root=tmp_path / "lr")
    assert imported.info.env_id == ENV_ID and imported.info.physics_dim == 5
    assert imported.info.env_kwargs == read_info(expert).env_kwargs
    for ep, ref in zip(imported.episodes, read_episodes(expert), strict=True):
        np.testing.assert_allclose(ep.observations, ref.observations, rtol=0, atol=F32)
        np.testing.assert_allclose(ep.actions, ref.actions, rtol=0, atol=F32)
        np.testing.assert_allclose(ep.goals, ref.goals, rtol=0, atol=F32)
        np.testing.assert_array_equal(ep.physics, ref.physics)  # float64 feature: exact
        np.testing.assert_array_equal(ep.time, ref.time)
        np.testing.assert_array_equal(ep.goal_reached, ref.goal_reached)


def test_lerobot_v21_folder_gets_the_conversion_command(tmp_path):
    (tmp_path / "meta").mkdir()
    (tmp_path / "meta/info.json").write_text(json.dumps({"codebase_version": "v2.1", "fps": 30}))
    with pytest.raises(UserError) as err:
        read_lerobot("me/old", "old", root=tmp_path)
    command = (
        "python -m lerobot.scripts.convert_dataset_v21_to_v30 --repo-id=me/old "
        f"--root={tmp_path} --push-to-hub=false"
    )
    assert command in str(err.value)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (
            {"state_features": ["observation.nope"]},
            r"no feature 'observation.nope'; available: .*action",
        ),
        ({"action_feature": "observation.images.cam"}, "image .*not a numeric vector"),
    ],
)
def test_lerobot_bad_features(lerobot_arm, kwargs, message):
    with pytest.raises(UserError, match=message):
        read_lerobot("test/arm", "arm", root=lerobot_arm[0], **kwargs)


def test_lerobot_not_a_dataset_and_empty(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(
        UserError, match=r"not a LeRobot dataset: no meta/info.json \(it holds notes.txt\)"
    ):
        read_lerobot("me/x", "x", root=tmp_path)
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {"action": {"dtype": "float32", "shape": (2,), "names": None}}
    LeRobotDataset.create("me/empty", fps=10, features=features, root=tmp_path / "e").finalize()
    with pytest.raises(UserError, match="empty"):
        read_lerobot("me/empty", "e", root=tmp_path / "e")


# --- D4RL ----------------------------------------------------------------------------------------


def test_d4rl_maze2d_import_matches_frame_by_frame(d4rl_file):
    path, written = d4rl_file
    imported = read_d4rl(path, "d", env_id=ENV_ID)
    episodes = list(imported.episodes)
    assert [len(e) for e in episodes] == [200, 160, 120]
    assert [bool(e.terminals[-1]) for e in episodes] == [True, False, False]
    assert imported.info.generator["episode_ends"] == {"terminals": 1, "timeouts": 2}
    assert imported.info.generator["coordinate_map"]["position_matrix"] == [[0, 1], [-1, 0]]
    for ep, ref in zip(episodes, written, strict=True):
        np.testing.assert_allclose(ep.observations, ref["observations"], rtol=0, atol=F32)
        np.testing.assert_allclose(ep.actions, ref["actions"], rtol=0, atol=F32)
        np.testing.assert_allclose(ep.goals, ref["goals"], rtol=0, atol=F32)
        np.testing.assert_array_equal(ep.rewards, ref["rewards"].astype(np.float64))
        np.testing.assert_allclose(np.diff(ep.time), DT, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(ep.physics[:, 0], ep.time)
        np.testing.assert_allclose(ep.physics[:, 1:], ep.observations, rtol=0, atol=F32)
    starts = [e.time[0] for e in episodes]
    assert starts == pytest.approx([0.0, 200 * DT, 360 * DT])  # one clock across episodes


def test_maze2d_map_matches_both_mazes_cells_and_published_data():
    env = make_maze_env("PointMaze_Large-v3")
    layout, maze = maze_layout(env), maze_of(env)
    env.close()
    mapping = Maze2dMap.for_layout(layout)
    cells = np.array(free_cells(maze), dtype=float)
    np.testing.assert_allclose(
        mapping.positions(cells - 0.2), [cell_to_xy(maze, tuple(c)) for c in cells.astype(int)]
    )
    # maze2d-large-v1's observation extremes per axis (as published with the dataset's users):
    # the ball's reachable area in Large is |x| <= 4.9, |y| <= 3.4 (cells minus the 0.1 m radius).
    lo, hi = mapping.positions(np.array([[0.39643136, 0.44179875], [7.2163844, 10.219488]]))
    np.testing.assert_allclose([lo[0], hi[0], lo[1], hi[1]], [-4.9, 4.9, 3.4, -3.4], atol=0.05)


def _h5(path: Path, **arrays) -> Path:
    with h5py.File(path, "w") as f:
        for key, value in arrays.items():
            f[key.replace("__", "/")] = value
    return path


OK = {"observations": np.zeros((10, 4)), "actions": np.zeros((10, 2)), "timeouts": np.eye(10)[9]}


@pytest.mark.parametrize(
    ("arrays", "kwargs", "message"),
    [
        (
            {"observations": OK["observations"], "timeouts": OK["timeouts"]},
            {},
            r"no array 'actions'; available: observations, timeouts",
        ),
        (
            {**OK, "actions": np.zeros((9, 2))},
            {},
            r"different lengths \(observations: 10, actions: 9",
        ),
        ({**OK, "observations": np.array([b"a"] * 10)}, {}, "`observations` is not numeric"),
        ({k: v[:0] for k, v in OK.items()}, {}, "holds no steps"),
        (
            {"observations": OK["observations"], "actions": OK["actions"]},
            {},
            "neither `terminals` nor `timeouts`",
        ),
        (OK, {"env_id": ""}, r"set ingest.d4rl.control_period"),
        ({**OK, "observations": np.zeros((10, 11))}, {"env_id": ENV_ID}, "not a maze2d file"),
    ],
)
def test_d4rl_bad_files(tmp_path, arrays, kwargs, message):
    with pytest.raises(UserError, match=message):
        read_d4rl(_h5(tmp_path / "bad.hdf5", **arrays), "bad", **kwargs)


def test_d4rl_not_hdf5_and_generic_file(tmp_path):
    (tmp_path / "x.hdf5").write_text("not hdf5")
    with pytest.raises(UserError, match="not an HDF5 file"):
        read_d4rl(tmp_path / "x.hdf5", "x")
    n = 30  # a locomotion-like file: 11-d observations, physics from infos/qpos + infos/qvel
    path = _h5(
        tmp_path / "hopper.hdf5",
        observations=np.ones((n, 11)),
        actions=np.ones((n, 3)),
        terminals=np.eye(n)[[12, 29]].any(0),
        infos__qpos=np.ones((n, 6)),
        infos__qvel=np.ones((n, 6)),
    )
    imported = read_d4rl(path, "hopper", control_period=0.008)
    episodes = list(imported.episodes)
    assert [len(e) for e in episodes] == [13, 17] and imported.info.env_id == ""
    assert episodes[1].physics.shape == (17, 13) and episodes[1].time[0] == pytest.approx(
        13 * 0.008
    )


# --- Minari --------------------------------------------------------------------------------------


def test_minari_import_matches_frame_by_frame(minari_dir):
    path, written = minari_dir
    imported = read_minari("m", path=path)
    info = imported.info
    assert info.env_id == ENV_ID and info.env_kwargs["continuing_task"] is True
    assert info.env_kwargs["maze_map"] == maze_layout_of(ENV_ID)["maze_map"]
    assert info.state_names == ["x", "y", "vx", "vy"] and info.physics_dim == 5
    start = 0
    for ep, ref in zip(imported.episodes, written, strict=True):
        n = len(ref["act"])
        assert len(ep) == n  # N + 1 observations in Minari, N here
        np.testing.assert_array_equal(ep.observations, ref["obs"])
        np.testing.assert_array_equal(ep.actions, ref["act"].astype(np.float64))
        np.testing.assert_array_equal(ep.goals, ref["goal"])
        np.testing.assert_allclose(ep.time, (start + np.arange(n)) * DT, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(ep.physics[:, 1:], ref["obs"])
        start += n


def maze_layout_of(env_id: str) -> dict:
    env = make_maze_env(env_id)
    try:
        return maze_layout(env)
    finally:
        env.close()


def test_minari_bad_inputs(minari_dir, tmp_path, monkeypatch):
    path = minari_dir[0]
    with pytest.raises(
        UserError,
        match=r"no observation key 'nope'; available: achieved_goal, desired_goal, observation",
    ):
        read_minari("m", path=path, state_keys=["nope"])
    with pytest.raises(UserError, match="observations are dicts: set ingest.minari.state_keys"):
        read_minari("m", path=path, state_keys=[])
    with pytest.raises(UserError, match="is not a Minari dataset"):
        read_minari("m", path=tmp_path)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(path.parents[1]))
    with pytest.raises(UserError, match="'test/other-v0' not found.*local datasets: test/umaze-v0"):
        read_minari("m", dataset_id="test/other-v0")
    assert read_minari("m", dataset_id="test/umaze-v0").frames == 100


# --- through the CLI: ingest, then an unchanged segment -----------------------------------------


def _params(tmp_path: Path, ingest: dict) -> list[str]:
    (tmp_path / "params.yaml").write_text(
        yaml.safe_dump({"ingest": ingest, "segment": {"window": 20}})
    )
    return ["--params", str(tmp_path / "params.yaml"), "--data", str(tmp_path / "data")]


@pytest.mark.parametrize("source", ["lerobot", "d4rl", "minari"])
def test_cli_ingest_then_segment(source, tmp_path, request, expert, caplog):
    if source == "lerobot":
        with caplog.at_level(logging.INFO):
            exported = runner.invoke(app, ["export", "lerobot", str(expert), str(tmp_path / "lr")])
        assert exported.exit_code == 0, exported.output
        said = [*caplog.messages, *exported.output.splitlines()]
        assert len([line for line in said if "wrote" in line]) == 1, said  # once, not twice
        section = {"root": str(tmp_path / "lr")}
    elif source == "d4rl":
        section = {"path": str(request.getfixturevalue("d4rl_file")[0]), "env_id": ENV_ID}
    else:
        section = {"path": str(request.getfixturevalue("minari_dir")[0])}
    common = _params(tmp_path, {"name": "imported", "source": source, source: section})
    for command in ("ingest", "segment"):
        result = runner.invoke(app, [command, *common])
        assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "data/reports/ingest/report.json").read_text())
    assert report["n_problems"] == 0  # the maze checks ran (walls, bounds, physics) and passed
    assert read_info(tmp_path / "data/demos/imported.mcap").source == source
    assert (tmp_path / "data/segments/imported/segments.safetensors").exists()


def test_cli_bad_import_is_one_line_and_leaves_no_file(tmp_path):
    _h5(
        tmp_path / "bad.hdf5",
        observations=np.zeros((10, 4)),
        actions=np.zeros((9, 2)),
        timeouts=np.ones(10),
    )
    common = _params(
        tmp_path, {"name": "bad", "source": "d4rl", "d4rl": {"path": str(tmp_path / "bad.hdf5")}}
    )
    result = runner.invoke(app, ["ingest", *common])
    assert result.exit_code == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "different lengths" in lines[0], result.stderr
    demos = tmp_path / "data/demos"
    assert not demos.exists() or not any(demos.iterdir())


def test_cli_export_refuses_to_overwrite(expert, tmp_path):
    (tmp_path / "lr").mkdir()
    (tmp_path / "lr/keep.txt").write_text("mine")
    result = runner.invoke(app, ["export", "lerobot", str(expert), str(tmp_path / "lr")])
    assert result.exit_code == 1 and "--overwrite" in result.stderr
    assert (tmp_path / "lr/keep.txt").read_text() == "mine"
