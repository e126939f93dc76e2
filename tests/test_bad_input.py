"""Bad input, the last holes (issue 38): each case is one line naming the file or key and what to
do, a non-zero exit, no traceback, and nothing written or left behind.

- Files read back (model config.json, resume state.json, segments.json, an expert's actor.json)
  are validated with typed models: wrong types, signs and non-finite numbers name file and field.
- A stage's outputs are checked before its work and published together at its end, or not at all.
- Messages never suggest an unsafe load, name our temporaries, or dump a whole params section.
- Values that cannot work are refused (non-finite floats, reach above the horizon, an OGBench file
  whose data are from another maze than `ingest.ogbench.env_id`).
- A killed run's temporaries are removed by the next successful run of the same output.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
import yaml
from factories import (
    kill_an_ingest_while_it_writes,
    make_info,
    make_skill_episodes,
    one_line_error,
    skill_model_config,
)
from typer.testing import CliRunner

from cli import _os_error_message, app
from pipeline.config import load_params
from pipeline.errors import UserError
from pipeline.io import clean_stale_temps, staged_outputs
from pipeline.model import SkillModel, load_model, save_model
from pipeline.model.checkpoint import load_dynamics, load_policy, save_dynamics, save_policy
from pipeline.model.dynamics import DynamicsModel
from pipeline.model.policy import GaussianPolicy
from pipeline.paths import Paths
from pipeline.segments import build_segments, load_segments, save_segments

runner = CliRunner()
SPLIT = {"train": 0.8, "validation": 0.1, "test": 0.1}
TINY = {"ingest": {"name": "tiny", "episodes": 6, "episode_steps": 150, "seed": 1}}


def _one_line_error(result) -> str:
    """The CLI's one-line error: exit status 1, `error: ...` on stderr, no traceback."""
    assert result.exit_code == 1, result.output
    lines = result.stderr.strip().splitlines()  # an import's progress bar may come first
    assert [line.startswith("error: ") for line in lines][-1:] == [True], result.stderr
    assert sum(line.startswith("error") for line in lines) == 1, result.stderr
    assert "Traceback" not in result.output
    return lines[-1]


def _edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def _files(root: Path) -> dict[str, bytes]:
    """Every file under `root` (relative path -> bytes): what a failed run must not change."""
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def _temps(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.name.startswith((".tmp-", ".old-"))]


# --- 1. values of the right shape, but the wrong type or sign, in files read back -------------


@pytest.fixture
def skill_dir(tmp_path) -> Path:
    model = SkillModel(skill_model_config(4, 2, z_dim=3, hidden=8))
    save_model(model, tmp_path / "model", {"window": 11, "step": 5})
    return tmp_path / "model"


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("hidden", "big", "bad value for 'model.hidden': Input should be a valid integer"),
        ("z_dim", -16, "bad value for 'model.z_dim': Input should be greater than or equal to 1"),
        ("min_std", float("nan"), "bad value for 'model.min_std': Input should be a finite"),
        ("tawm_shared_std", "perhaps", "bad value for 'model.tawm_shared_std'"),
        ("action_low", [0.0], "action_low and action_high come together"),
    ],
)
def test_a_model_config_with_a_wrong_type_or_sign_names_file_and_field(
    skill_dir, field, value, message
):
    _edit_json(skill_dir / "config.json", lambda m: m["model"].update({field: value}))
    text = one_line_error(lambda: load_model(skill_dir))
    assert message in text and str(skill_dir / "config.json") in text
    assert "re-run `oposm train`" in text


def test_the_model_config_s_other_fields_are_checked_too(skill_dir):
    _edit_json(skill_dir / "config.json", lambda m: m.update(window=1))
    assert "bad value for 'window'" in one_line_error(lambda: load_model(skill_dir))
    _edit_json(skill_dir / "config.json", lambda m: m.update(window=11, info={"env_id": 3}))
    assert "bad value for 'info.env_id'" in one_line_error(lambda: load_model(skill_dir))
    _edit_json(skill_dir / "config.json", lambda m: m.update(info=None, model="x"))
    assert "bad value for 'model'" in one_line_error(lambda: load_model(skill_dir))
    (skill_dir / "config.json").write_text('{"format_version": 1, "model": {"z_dim": 3')
    assert "truncated" in one_line_error(lambda: load_model(skill_dir))


def test_a_dynamics_or_policy_config_with_a_bad_value_names_file_and_field(tmp_path):
    from factories import dynamics_config, policy_config

    save_dynamics(DynamicsModel(dynamics_config(4, 2, hidden=8)), tmp_path / "dyn", {})
    _edit_json(tmp_path / "dyn/config.json", lambda m: m["model"].update(hidden=0))
    text = one_line_error(lambda: load_dynamics(tmp_path / "dyn"))
    assert "dyn/config.json: bad value for 'model.hidden'" in text and "oposm dynamics" in text
    save_policy(GaussianPolicy(policy_config(4, 2, (0, 1), hidden=8)), tmp_path / "p", "gcbc", {})
    _edit_json(tmp_path / "p/config.json", lambda m: m["model"].update(goal_dims=[0, 9]))
    text = one_line_error(lambda: load_policy(tmp_path / "p", "gcbc"))
    assert "goal_dims [0, 9] must be state dims" in text and "oposm gcbc" in text


@pytest.fixture(scope="module")
def segments():
    episodes = make_skill_episodes(n_episodes=12, length=120, seed=0)
    return build_segments(episodes, make_info("skills", physics_dim=0), 11, 1, SPLIT, seed=0)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda m: m.update(stride=-1), "'stride'"),
        (lambda m: m["stats"]["state_std"].__setitem__(0, float("nan")), "'stats.state_std.0'"),
        (lambda m: m["stats"]["action_std"].__setitem__(0, 0.0), "'stats.action_std.0'"),
        (lambda m: m["dataset"].update(control_period=-0.01), "'dataset.control_period'"),
        (lambda m: m["dataset"].update(state_names="xy"), "'dataset.state_names'"),
    ],
)
def test_a_segments_index_with_a_bad_value_names_file_and_field(tmp_path, segments, edit, message):
    save_segments(segments, tmp_path / "seg")
    _edit_json(tmp_path / "seg/segments.json", edit)
    text = one_line_error(lambda: load_segments(tmp_path / "seg"))
    assert text.startswith(f"{tmp_path / 'seg/segments.json'}: bad value for ")
    assert message in text and "re-run `oposm segment`" in text


def test_an_actor_description_with_a_bad_value_names_file_and_field(tmp_path):
    from pipeline.ant_expert.actor import ActorSpec, DirectionActor, load_actor, save_actor

    path = tmp_path / "actor.safetensors"
    save_actor(DirectionActor(ActorSpec(29, 8, [16], "gelu", [-1.0] * 8, [1.0] * 8)), path)
    for edit, message in [
        (lambda m: m.update(hidden=["big"]), "bad value for 'hidden.0'"),
        (lambda m: m.update(obs_dim=-29), "bad value for 'obs_dim'"),
        (lambda m: m.update(activation="tanh"), "bad value for 'activation'"),
        (lambda m: m.update(action_high=[1.0] * 7), "action_high has 7 values for 8 dims"),
        (lambda m: m.update(action_low=[1.0] * 8), "below its action_high"),
    ]:
        good = path.with_suffix(".json").read_text()
        _edit_json(path.with_suffix(".json"), edit)
        text = one_line_error(lambda: load_actor(path))
        assert message in text and str(path.with_suffix(".json")) in text, text
        path.with_suffix(".json").write_text(good)


@pytest.fixture
def train_paths(tmp_path, segments) -> Paths:
    save_segments(segments, tmp_path / "data" / "segments" / "skills")
    return Paths(tmp_path / "data")


def _train(paths: Paths, **train):
    from pipeline.config import Params
    from stages import train as stage

    small = {"z_dim": 4, "hidden": 16, "batch_size": 16, "val_windows": 50, "device": "cpu"}
    steps = {"max_steps": 20, "eval_every": 10, "checkpoint_every": 10}
    params = Params.model_validate({"ingest": {"name": "skills"}, "train": small | steps | train})
    with torch.random.fork_rng():
        return stage.run(params, paths, progress_bar=False)


def _resume_dir(paths: Paths) -> Path:
    (scratch,) = (paths.root / "scratch" / "train").iterdir()
    return scratch / "resume"


def test_a_resume_state_with_a_wrong_type_names_file_and_field(train_paths):
    _train(train_paths)
    state = _resume_dir(train_paths) / "state.json"
    _edit_json(state, lambda m: m["progress"].update(step="abc"))
    text = one_line_error(lambda: _train(train_paths, max_steps=30))
    assert f"{state}: bad value for 'progress.step'" in text and "'>' not supported" not in text
    assert f"delete {state.parent} to start over" in text
    _edit_json(state, lambda m: m["progress"].update(step=20, elapsed_s=-1.0))
    assert "'progress.elapsed_s'" in one_line_error(lambda: _train(train_paths, max_steps=30))


# --- 2. outputs checked before the work, published together or not at all --------------------


def test_validate_with_recordings_a_file_fails_first_and_changes_nothing(tmp_path):
    """A file where an output folder must be: one line before any work (no segments needed to
    get there), and the previous run's CSVs and report stay as they were."""
    data = tmp_path / "data"
    (data / "reports/validate").mkdir(parents=True)
    for name in ("error_vs_horizon.csv", "end_positions.csv", "report.json"):
        (data / "reports/validate" / name).write_text(f"old {name}\n")
    (data / "recordings").write_text("a file, not a folder\n")
    before = _files(tmp_path)
    line = _one_line_error(runner.invoke(app, ["validate", "--data", str(data)]))
    assert f"{data / 'recordings'} is a file, and a folder is needed there" in line
    assert "use `--data` elsewhere" in line and "File exists" not in line
    assert _files(tmp_path) == before and not _temps(tmp_path)


def test_deploy_with_metrics_under_a_file_fails_first_and_writes_nothing(tmp_path):
    (tmp_path / "afile").write_text("x\n")
    data = tmp_path / "data"
    args = ["deploy", "--data", str(data), "--metrics", str(tmp_path / "afile/sub")]
    line = _one_line_error(runner.invoke(app, args))
    assert f"{tmp_path / 'afile'} is a file, and a folder is needed there" in line
    assert "pass `--metrics` another folder" in line
    assert not data.exists()  # no report.json, episodes.json, overview.rrd


def test_read_only_data_fails_before_the_work(tmp_path, monkeypatch):
    """On a read-only data root validate says so up front, instead of after its rollouts."""
    from pipeline import io as pio

    data = tmp_path / "data"
    data.mkdir()
    real_access = os.access

    def access(path, mode) -> bool:  # what a read-only disk (or a folder of another user) says
        return False if Path(path) == data and mode & os.W_OK else real_access(path, mode)

    monkeypatch.setattr(pio.os, "access", access)
    monkeypatch.setattr(pio, "_read_only", lambda p: True)
    monkeypatch.setattr("stages.validate.load_segments", lambda *a: pytest.fail("did the work"))
    line = _one_line_error(runner.invoke(app, ["validate", "--data", str(data)]))
    assert f"{data} is on a read-only file system; use `--data` elsewhere" in line
    monkeypatch.setattr(pio, "_read_only", lambda p: False)
    line = _one_line_error(runner.invoke(app, ["validate", "--data", str(data)]))
    assert f"no permission to write in {data}; make it writable for you" in line


def test_staged_outputs_are_published_together_or_not_at_all(tmp_path):
    a, b, folder = tmp_path / "r/a.json", tmp_path / "m/b.json", tmp_path / "rec"
    with staged_outputs([a, b], [folder]) as out:
        out.write_json(a, 1)
        out.write_json(b, 1)
        (out.folder(folder) / "x.rrd").write_text("1")
    before = _files(tmp_path)
    with pytest.raises(RuntimeError), staged_outputs([a, b], [folder]) as out:
        out.write_json(a, 2)
        (out.folder(folder) / "y.rrd").write_text("2")
        raise RuntimeError("failed before b was written")
    assert _files(tmp_path) == before and not _temps(tmp_path)
    with staged_outputs([a], []) as out:
        out.write_json(a, 3)
        out.write_json(b, 3)  # not named up front: staged all the same
        out.folder(folder)  # an empty folder replaces the old one whole
    assert json.loads(a.read_text()) == json.loads(b.read_text()) == 3
    assert list(folder.iterdir()) == [] and not _temps(tmp_path)


def test_a_failed_run_removes_the_folders_it_made(tmp_path):
    with pytest.raises(RuntimeError), staged_outputs() as out:
        out.write_json(tmp_path / "new/deep/report.json", 1)
        raise RuntimeError
    assert list(tmp_path.iterdir()) == []


# --- 3. messages that suggest something unsafe or wrong ---------------------------------------


@pytest.mark.parametrize(
    "damage",
    [
        lambda p: p.write_bytes(p.read_bytes()[:3000]),  # truncated zip
        lambda p: p.write_text("garbage"),
        lambda p: p.write_bytes(b""),
        lambda p: p.write_bytes(__import__("pickle").dumps({"a": object()})),  # not weights-only
    ],
    ids=["truncated", "garbage", "empty", "arbitrary pickle"],
)
def test_a_damaged_optimizer_state_never_suggests_an_unsafe_load(train_paths, damage):
    _train(train_paths)
    optim = _resume_dir(train_paths) / "optim.pt"
    damage(optim)
    text = one_line_error(lambda: _train(train_paths))
    assert f"{optim} is damaged, or not the optimizer state `oposm train` writes" in text
    assert "weights_only" not in text and "pickle" not in text.lower()


def test_an_hdf5_file_named_npz_says_what_it_is_and_never_suggests_allow_pickle(tmp_path):
    from pipeline.sources.ogbench import read_ogbench

    with h5py.File(tmp_path / "data.npz", "w") as f:
        f["observations"] = np.zeros((3, 2))
    text = one_line_error(lambda: read_ogbench(tmp_path / "data.npz", "x", "pointmaze-medium-v0"))
    assert "is an HDF5 file, not a .npz" in text and "ingest.source=d4rl" in text
    np.savez(tmp_path / "objects.npz", observations=np.array([{"a": 1}], dtype=object))
    text = one_line_error(
        lambda: read_ogbench(tmp_path / "objects.npz", "x", "pointmaze-medium-v0")
    )
    assert "is not an OGBench dataset" in text
    for said in ("allow_pickle", "pickle.load", "trust"):
        assert said not in text


def test_model_option_naming_another_kind_of_folder_says_what_it_holds(
    tmp_path, segments, skill_dir
):
    save_segments(segments, tmp_path / "seg")
    text = one_line_error(lambda: load_model(tmp_path / "seg"))
    assert "holds segments (what `oposm segment` writes), not a skill model" in text
    assert "run `oposm train` first" not in text
    from factories import dynamics_config

    save_dynamics(DynamicsModel(dynamics_config(4, 2, hidden=8)), tmp_path / "dyn", {})
    assert "holds a single-step dynamics model" in one_line_error(
        lambda: load_model(tmp_path / "dyn")
    )
    assert "holds a skill model" in one_line_error(lambda: load_dynamics(skill_dir))
    (tmp_path / "file").write_text("x")
    assert "is a file, not a skill model checkpoint folder" in one_line_error(
        lambda: load_model(tmp_path / "file")
    )


# --- 4. messages that name our temporaries or give no next step -------------------------------


def test_nan_in_a_d4rl_file_names_the_hdf5_not_our_temporary(tmp_path):
    n = 30
    obs = np.ones((n, 11))
    obs[5, 3] = np.nan
    with h5py.File(tmp_path / "hopper.hdf5", "w") as f:
        f["observations"], f["actions"] = obs, np.ones((n, 3))
        f["terminals"] = np.eye(n)[[12, 29]].any(0)
    data = tmp_path / "data"
    d4rl = {"path": str(tmp_path / "hopper.hdf5"), "control_period": 0.01}
    (tmp_path / "p.yaml").write_text(
        yaml.safe_dump({"ingest": {"name": "hop", "source": "d4rl", "d4rl": d4rl}})
    )
    line = _one_line_error(
        runner.invoke(app, ["ingest", "-p", str(tmp_path / "p.yaml"), "--data", str(data)])
    )
    assert line.startswith(f"error: {tmp_path / 'hopper.hdf5'}: episode 0, step 5")
    assert ".tmp-" not in line and "fix the source data" in line
    assert not data.exists()  # the folders it made for its outputs are gone again


@pytest.mark.parametrize(
    ("code", "strerror", "hint"),
    [
        (errno.EEXIST, "File exists", "is a file, and a folder is needed there; move or delete"),
        (
            errno.ENOTDIR,
            "Not a directory",
            "is a file, and a folder is needed there; move or delete",
        ),
        (errno.EACCES, "Permission denied", "make it readable and writable for you"),
        (errno.EROFS, "Read-only file system", "use `--data` on a writable disk"),
    ],
)
def test_os_errors_say_what_to_do(tmp_path, code, strerror, hint):
    (tmp_path / "data").write_text("a file\n")
    where = (
        tmp_path / "data"
        if code == errno.EEXIST
        else tmp_path / "data/reports/.tmp-x.json.abcdefgh"
    )
    text = _os_error_message(OSError(code, strerror, str(where)), data_option=True)
    assert (
        hint in text
        and ".tmp-" not in text
        and text.endswith("`--data` elsewhere)") == (code != errno.EROFS)
    )


def test_a_goal_in_a_wall_names_the_key_and_the_nearest_free_cell():
    from pipeline.envs.spec import PointMazeSpec
    from pipeline.evaluation.tasks import check_goal, layout_cell

    layout = PointMazeSpec.create("PointMaze_Medium-v3").layout
    text = one_line_error(lambda: check_goal(layout, np.array([0.0, 3.5])))
    assert text.startswith("deploy.goal [0.0, 3.5] is inside a wall")
    suggested = json.loads(text.rsplit("deploy.goal=", 1)[1])
    row, col = layout_cell(layout, *suggested)
    assert layout["maze_map"][row][col] != 1  # a free cell
    check_goal(layout, np.array(suggested))
    assert "set deploy.goal=" in one_line_error(lambda: check_goal(layout, np.array([0.0, -9.0])))


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("deploy.planner.elites=200", "bad values in 'deploy.planner': elites (200) must be <="),
        ("deploy.llp.elites=200", "bad values in 'deploy.llp': elites (200) must be <="),
        ("deploy.subgoals.reach=20", "subgoals.reach (20) must be <= planner.horizon (10)"),
        ("train.lr_e=inf", "bad value for 'train.lr_e': Input should be a finite number"),
        ("train.lr_m=.nan", "bad value for 'train.lr_m': Input should be a finite number"),
        ("dynamics.lr=.inf", "bad value for 'dynamics.lr'"),
        ("deploy.success_radius=.inf", "bad value for 'deploy.success_radius'"),
    ],
)
def test_values_that_cannot_work_are_refused_without_dumping_the_section(override, message):
    text = one_line_error(lambda: load_params("params.yaml", [override]))
    assert message in text and "{" not in text  # never the whole section's dict


def test_reach_above_the_horizon_is_refused_even_while_subgoals_are_off():
    params = load_params("params.yaml", ["deploy.subgoals.reach=10"])  # = horizon: fine
    assert params.deploy.subgoals.enabled
    with pytest.raises(UserError, match="lower subgoals.reach or raise planner.horizon"):
        load_params("params.yaml", ["deploy.subgoals.reach=11"])
    with pytest.raises(UserError, match="lower subgoals.reach or raise planner.horizon"):
        load_params("params.yaml", ["deploy.subgoals.enabled=false", "deploy.subgoals.reach=11"])


def test_an_ogbench_file_that_names_no_maze_must_fit_env_id_and_says_which_maze_it_fits(tmp_path):
    from pipeline.sources.ogbench import read_ogbench
    from pipeline.sources.ogbench.info import ogbench_spec

    def write(path: Path, env_id: str) -> None:
        centers = np.asarray(ogbench_spec(env_id).layout["free_cell_centers"], np.float32)
        n = len(centers)
        terminals = np.eye(n, dtype=bool)[-1]
        np.savez(
            path, observations=centers, actions=np.zeros((n, 2), np.float32), terminals=terminals
        )

    write(tmp_path / "mine.npz", "pointmaze-large-v0")
    text = one_line_error(lambda: read_ogbench(tmp_path / "mine.npz", "x", "pointmaze-medium-v0"))
    assert (
        "its name names no maze" in text and "set ingest.ogbench.env_id=pointmaze-large-v0" in text
    )
    assert len(list(read_ogbench(tmp_path / "mine.npz", "x", "pointmaze-large-v0").episodes)) == 1
    ant = {"observations": np.zeros((4, 29)), "actions": np.zeros((4, 8)), "terminals": np.ones(4)}
    np.savez(tmp_path / "ant.npz", **ant)
    text = one_line_error(lambda: read_ogbench(tmp_path / "ant.npz", "x", "pointmaze-medium-v0"))
    assert "29 values per observation, pointmaze-medium-v0 has 2" in text
    assert "set ingest.ogbench.env_id=antmaze-" in text


# --- 6. leftovers of killed runs --------------------------------------------------------------


def test_a_successful_run_removes_only_the_stale_temporaries_of_its_own_outputs(tmp_path):
    demos = tmp_path / "data/demos"
    demos.mkdir(parents=True)
    stale = [".tmp-tiny.mcap.abcdefgh", ".tmp-.tmp-tiny.mcap.abcdefgh.ijk_mnop"]
    kept = [
        ".tmp-other.mcap.abcdefgh",
        ".tmp-tiny.mcap.abc",
        "tiny.mcap.abcdefgh",
        ".tmp-tiny.mcap.live0000",
    ]
    for name in stale + kept:
        (demos / name).write_text("x")
    (demos / ".tmp-tiny.mcap.dir_0000").mkdir()  # a killed folder write
    (demos / ".tmp-tiny.mcap.dir_0000/f").write_text("x")
    live = os.open(demos / ".tmp-tiny.mcap.live0000", os.O_RDONLY)  # a live writer's
    fcntl.flock(live, fcntl.LOCK_EX)
    try:
        (tmp_path / "p.yaml").write_text(yaml.safe_dump(TINY))
        args = ["ingest", "-p", str(tmp_path / "p.yaml"), "--data", str(tmp_path / "data")]
        result = runner.invoke(app, args)
        assert result.exit_code == 0, result.output
    finally:
        os.close(live)
    assert sorted(p.name for p in demos.iterdir()) == sorted([*kept, "tiny.mcap"])
    assert clean_stale_temps(demos / "tiny.mcap") == [demos / ".tmp-tiny.mcap.live0000"]


@pytest.mark.slow
def test_a_sigkilled_ingest_leaves_temporaries_the_next_run_removes(tmp_path):
    demos = kill_an_ingest_while_it_writes(tmp_path, "tiny")  # the pipeline's data/demos
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(TINY))
    result = runner.invoke(
        app, ["ingest", "-p", str(tmp_path / "p.yaml"), "--data", str(tmp_path / "data")]
    )
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in demos.iterdir()) == ["tiny.mcap"]


# --- 2 (again, end to end): a run that fails late keeps every old output --------------------

PROJECT = {
    "ingest": {"name": "tiny", "episodes": 6, "episode_steps": 150, "seed": 3},
    "segment": {"window": 20},
    "train": {"z_dim": 4, "hidden": 16, "max_steps": 20, "eval_every": 10, "val_windows": 50},
    "dynamics": {"hidden": 16, "max_steps": 30, "eval_every": 15, "val_transitions": 200},
    "validate": {"starts": 4, "skills": 2, "repeats": 1, "particles": 4, "record_starts": 1},
    "deploy": {
        "tasks": ["random_goal"],
        "episodes": 2,
        "num_envs": 2,
        "max_steps": 20,
        "record_episodes": 1,
        "planner": {"horizon": 3, "candidates": 8, "elites": 2, "iterations": 2},
    },
}


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    """A tiny real pipeline run through the CLI up to validate and deploy."""
    root = tmp_path_factory.mktemp("project")
    (root / "params.yaml").write_text(yaml.safe_dump(PROJECT))
    common = ["--params", str(root / "params.yaml"), "--data", str(root / "data")]
    for command in ("ingest", "segment", "train", "dynamics", "validate", "deploy"):
        result = runner.invoke(app, [command, *common])
        assert result.exit_code == 0, (command, result.output)
    return root, common


@pytest.mark.slow
@pytest.mark.parametrize(
    ("stage", "late"),
    [
        ("validate", "pipeline.viz.validate.write_recording"),  # after the CSVs are written
        ("deploy", "stages.deploy.write_overview"),  # after the episodes' recordings
    ],
)
def test_a_stage_failing_late_keeps_all_its_old_outputs(project, monkeypatch, stage, late):
    """Another seed: every output would change. The run fails after writing some of them, and
    none of the new ones replaces an old one."""
    root, common = project
    before = _files(root)

    def fails(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(args[0]))

    monkeypatch.setattr(late, fails)
    line = _one_line_error(runner.invoke(app, [stage, *common, "-S", f"{stage}.seed=1"]))
    assert "No space left on device" in line and ".tmp-" not in line
    after = _files(root)
    kept = {f for f in after if f.startswith("data/scratch/")} - set(before)
    # no new CSV beside an old report, no new report.json; only the work a rerun resumes from
    assert {f: b for f, b in after.items() if f not in kept} == before
    if stage == "deploy":  # its finished job is kept for the next run (`JobStore`)
        assert any(f.startswith("data/scratch/deploy/") for f in kept)
    assert not _temps(root / "data")
