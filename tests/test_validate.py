"""Open-loop validation: exact replay in MuJoCo, calibration, wall crossings, the single-step model
and a short real `oposm validate` run (tiny dataset, briefly trained models) through the CLI."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch
import yaml
from factories import make_info, make_skill_episodes, skill_model_config
from typer.testing import CliRunner

from cli import app
from pipeline.config import DynamicsParams
from pipeline.envs.batch import BatchSim
from pipeline.envs.maze.expert import ExpertConfig
from pipeline.envs.maze.generate import dataset_info, generate_episodes
from pipeline.envs.spec import PointMazeSpec
from pipeline.errors import UserError
from pipeline.evaluation.open_loop import choose_starts, restore, tawm_predictive
from pipeline.evaluation.open_loop_metrics import (
    EXPECTED_WITHIN,
    first_wall_crossing,
    gaussian_nll,
    points_in_walls,
    within_sigma,
)
from pipeline.model import SkillModel
from pipeline.model.checkpoint import load_dynamics, save_dynamics
from pipeline.model.rollout import rollout_skills
from pipeline.segments import build_segments, load_segments, save_segments
from pipeline.training.dynamics import fit_dynamics, transition_index

ENV_ID = "PointMaze_Medium-v3"
runner = CliRunner()


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """Small MLPs: one intra-op thread is faster, and immune to the 10x slowdowns that 2 spinning
    threads suffer on 2 cores shared with other jobs (this module: 25 s instead of 160 s)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="module")
def recorded():
    """3 x 300 steps of the noisy expert in Medium, as episodes (float64) and segments."""
    episodes = list(generate_episodes(ENV_ID, 3, 300, 11, ExpertConfig(), False))
    info = dataset_info(ENV_ID, "replay", 11, ExpertConfig(), 3, 300)
    split = {"train": 0.34, "validation": 0.33, "test": 0.33}
    return episodes, build_segments(episodes, info, 40, 1, split, seed=0)


def test_restored_states_replay_whole_windows_exactly(recorded):
    """The foundation of open-loop validation: restore s_0 of every 40-state window of a real
    recording, replay its 39 recorded actions in a fresh simulator, get the recorded states.

    With the recorded float64 actions the replay must match to 1e-12: MuJoCo is deterministic,
    the only difference from the recording is the solver warm start that restoring zeroes, which
    moves a state touching a wall by round-off (<= 2.2e-14 per step, tests/test_envs.py). Measured
    here: bit-exact on every window. The segments store actions as float32 (rounded by <= 2^-24
    relative); a unit of action changes velocity by <= 0.25 m/s per step, so after 39 steps the
    replay can drift by <= 39 * 0.25 * 6e-8 = 6e-7: 1e-6 (measured: 4e-8).
    """
    episodes, segments = recorded
    starts = np.concatenate([segments.starts[s] for s in ("train", "validation", "test")])
    actions64 = np.concatenate([ep.actions for ep in episodes])
    sim = BatchSim(PointMazeSpec.create(ENV_ID, **segments.info.env_kwargs), len(starts))
    for actions, atol in ((actions64, 1e-12), (segments.actions, 1e-6)):
        restore(sim, segments.physics[starts], segments.states[starts], [""] * len(starts))
        worst = 0.0
        for k in range(segments.horizon):
            assert not sim.step(actions[starts + k].astype(np.float64))
            worst = max(worst, np.abs(sim.observe() - segments.physics[starts + k + 1, 1:]).max())
        assert worst <= atol, worst


def test_unrestorable_states_are_user_errors(recorded):
    _, segments = recorded
    idx = segments.starts["test"][:3]
    sim = BatchSim(PointMazeSpec.create(ENV_ID, **segments.info.env_kwargs), 3)
    where = ["a", "b", "test episode 2, step 7"]
    moved = segments.physics[idx].copy()
    moved[2, 1] += 0.5  # physics from another moment than the observation
    with pytest.raises(UserError, match="test episode 2, step 7 cannot be restored"):
        restore(sim, moved, segments.states[idx], where)
    nan = segments.physics[idx].copy()
    nan[0, 3] = np.nan
    with pytest.raises(UserError, match="at a is not finite"):
        restore(sim, nan, segments.states[idx], where)
    with pytest.raises(UserError, match="another model"):
        restore(sim, segments.physics[idx, :4], segments.states[idx], where)


def test_starts_are_held_out_and_leave_room_for_the_chain(recorded):
    _, segments = recorded
    starts = choose_starts(segments, 50, span=78, seed=0)
    test_eps = segments.episodes_in("test")
    offsets = segments.episode_offsets
    assert len(starts) == 50 and np.all(np.diff(starts) > 0)
    for s in starts:
        e = np.searchsorted(offsets, s, side="right") - 1
        assert e in test_eps and s + 78 < offsets[e + 1]
    assert np.array_equal(starts, choose_starts(segments, 50, span=78, seed=0))
    with pytest.raises(UserError, match="lower validate.skills"):
        choose_starts(segments, 5, span=300, seed=0)
    no_test = build_segments(
        recorded[0], segments.info, 40, 1, {"train": 1, "validation": 0, "test": 0}
    )
    with pytest.raises(UserError, match="no test split"):
        choose_starts(no_test, 5, span=10, seed=0)


def test_calibration_of_synthetic_gaussians():
    """Samples from N(mean, std) fall within 1 / 2 std 68.3 % / 95.4 % of the time per dimension;
    a model claiming half the true std (overconfident) catches erf(0.5 / sqrt 2) = 38.3 %."""
    rng = np.random.default_rng(0)
    n = 40_000
    mean = rng.normal(size=(n, 3)) * 5
    std = rng.uniform(0.01, 3, size=(n, 3))
    x = mean + std * rng.normal(size=(n, 3))
    tol = 4 * math.sqrt(0.25 / n)  # 4 binomial standard deviations at worst (p = 0.5)
    for k, p in EXPECTED_WITHIN.items():
        np.testing.assert_allclose(within_sigma(x, mean, std, k), p, atol=tol)
    np.testing.assert_allclose(within_sigma(x, mean, std / 2, 1), math.erf(0.5 / 2**0.5), atol=tol)
    assert EXPECTED_WITHIN[1] == pytest.approx(0.6827, abs=1e-4)
    # The NLL is the Gaussian's, summed over dimensions: checked against the closed form.
    xt, mt, st = (torch.as_tensor(a[:5]) for a in (x, mean, std))
    closed = (0.5 * ((xt - mt) / st) ** 2 + st.log() + 0.5 * math.log(2 * math.pi)).sum(-1)
    torch.testing.assert_close(gaussian_nll(xt, mt, st), closed)


@pytest.fixture(scope="module")
def layout():
    return PointMazeSpec.create(ENV_ID).layout


def test_wall_crossing_on_hand_made_paths(layout):
    """Medium maze, unit cells: cell (row, col) spans x in [col - 4, col - 3] and y in
    [3 - row, 4 - row]. Row 1 is `1 0 0 1 1 0 0 1`, row 2 `1 0 0 1 0 0 0 1`, row 3 `1 1 0 0 ...`."""
    maze = layout["maze_map"]
    assert (
        maze[1][:5] == [1, 0, 0, 1, 1]
        and maze[2][:4] == [1, 0, 0, 1]
        and maze[3][:4] == [1, 1, 0, 0]
    )
    paths = {
        "stays in (1, 1)-(1, 2)": ([[-2.5, 2.5], [-2.0, 2.8], [-1.6, 2.2], [-1.15, 2.5]], 4),
        "walks into wall (1, 3) at step 2": (
            [[-2.5, 2.5], [-1.5, 2.5], [-0.5, 2.5], [0.5, 2.5]],
            2,
        ),
        "stands still, then leaps (1, 3)": ([[-1.5, 2.5], [-1.5, 2.5], [-1.5, 2.5], [1.5, 2.5]], 3),
        "vertical down column 2": ([[-1.5, 2.5], [-1.5, 2.0], [-1.5, 1.5], [-1.5, 0.6]], 4),
        "diagonal cutting wall (2, 3)": ([[-1.5, 1.5], [-1.2, 1.8], [-0.2, 1.8], [-0.5, 0.5]], 2),
        "diagonal through free (1, 1)-(2, 2)": (
            [[-2.9, 2.9], [-1.1, 1.1], [-1.1, 1.1], [-1.9, 1.9]],
            4,
        ),
    }
    got = first_wall_crossing(np.array([p for p, _ in paths.values()]), layout, chunk=4)
    assert dict(zip(paths, got.tolist(), strict=True)) == {k: t for k, (_, t) in paths.items()}
    # Cells are closed: a path through the corner a wall shares with free cells touches it.
    corner = np.array([[[-2.5, 1.5], [-1.5, 0.5]]])  # (2, 1) -> (3, 2) past wall (3, 1)'s corner
    assert first_wall_crossing(corner, layout).tolist() == [1]
    ends = np.array([[-2.5, 2.5], [-0.5, 2.5], [5.0, 0.0]])  # free, in a wall, off the map
    assert points_in_walls(ends, layout).tolist() == [False, True, True]


def _tiny_model(state_dim=4, seed=0):
    torch.manual_seed(seed)
    model = SkillModel(skill_model_config(state_dim, 2, z_dim=3, hidden=16)).eval()
    model.set_normalization(np.zeros(4), np.ones(4) * 2, np.zeros(2), np.ones(2))
    return model


def test_tawm_predictive_is_exact_for_one_skill_and_chains_means():
    model = _tiny_model()
    s0, z = torch.randn(5, 4), torch.randn(5, 3, 3)
    chain = rollout_skills(model, s0, z=z)
    mean, std = tawm_predictive(model, s0, z, 256, torch.Generator().manual_seed(0))
    one_mean, one_std = model.predict_end(s0, z[:, 0])
    torch.testing.assert_close(mean[:, 0], one_mean)
    torch.testing.assert_close(std[:, 0], one_std)
    torch.testing.assert_close(chain.states[:, 1], one_mean)
    torch.testing.assert_close(chain.std[:, 0], one_std)
    torch.testing.assert_close(chain.states[:, 2], model.predict_end(one_mean, z[:, 1])[0])
    assert mean.shape == std.shape == (5, 3, 4) and torch.isfinite(std).all()


def test_single_step_model_learns_and_round_trips(tmp_path):
    """On a synthetic world with x' = x + 0.05 a, v' = a the model beats predicting no change
    by far, and a saved model predicts the same after loading."""
    episodes = make_skill_episodes(n_episodes=12, length=120, seed=1)
    split = {"train": 0.7, "validation": 0.3, "test": 0.0}
    segments = build_segments(episodes, make_info("skills", 0), 11, 1, split, seed=0)
    fit = DynamicsParams(hidden=32, batch_size=128, lr=3e-3, max_steps=400, eval_every=200)
    model, metrics = fit_dynamics(segments, fit, torch.device("cpu"))
    idx = transition_index(segments, "validation")
    s, a, s1 = (
        torch.as_tensor(x)
        for x in (segments.states[idx], segments.actions[idx], segments.states[idx + 1])
    )
    no_change = float((s1 - s).square().sum(-1).mean().sqrt())
    assert metrics["val_rmse"] < 0.2 * no_change
    rollout = model.rollout(s[:4], a[:4, None].expand(-1, 3, -1))
    assert rollout.shape == (4, 4, 4) and torch.equal(rollout[:, 0], s[:4])
    save_dynamics(model, tmp_path / "dyn", {"info": {}})
    loaded, meta = load_dynamics(tmp_path / "dyn")
    torch.testing.assert_close(loaded.predict(s, a)[0], model.predict(s, a)[0])
    assert meta["model"]["hidden"] == 32
    with pytest.raises(UserError, match="oposm dynamics"):
        load_dynamics(tmp_path / "nothing")


# -- the real stage through the CLI ---------------------------------------------------------------

TINY = {
    "ingest": {"name": "tiny", "episodes": 6, "episode_steps": 150, "seed": 3},
    "segment": {"window": 20},
    "train": {"z_dim": 4, "hidden": 32, "max_steps": 40, "eval_every": 20, "val_windows": 50},
    "dynamics": {"hidden": 32, "max_steps": 100, "eval_every": 50},
    "validate": {"starts": 6, "skills": 2, "repeats": 2, "particles": 8, "record_starts": 1},
}


def _one_line_error(result) -> str:
    assert result.exit_code == 1, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    return lines[0]


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    """A tiny real dataset, a skill model and a dynamics model trained briefly on it, validated."""
    root = tmp_path_factory.mktemp("validate")
    (root / "params.yaml").write_text(yaml.safe_dump(TINY))
    common = ["--params", str(root / "params.yaml"), "--data", str(root / "data")]
    for command in ("ingest", "segment", "train", "dynamics", "validate"):
        result = runner.invoke(app, [command, *common])
        assert result.exit_code == 0, (command, result.output)
    return root, common


def test_validate_writes_report_plots_and_recording(workdir):
    root, common = workdir
    data = root / "data"
    report = json.loads((data / "reports/validate/report.json").read_text())
    assert report["skill_horizon"] == 19 and report["rollouts_per_mode"] == 12
    assert report["real_wall_crossing"] == 0.0  # real MuJoCo paths never enter a wall
    for mode in ("prior", "posterior"):
        assert list(report[mode]) == ["skills_1", "skills_2"]
        m = report[mode]["skills_2"]
        assert m["steps"] == 38
        for key in (
            "tawm_error_mean",
            "single_step_error_median",
            "tawm_nll",
            "no_model_error_mean",
        ):
            assert math.isfinite(m[key])
        for key in ("tawm_within_1sigma", "tawm_within_2sigma", "single_step_wall_crossing"):
            assert 0 <= m[key] <= 1
        assert m["tawm_within_1sigma"] <= m["tawm_within_2sigma"]
        assert set(m["tawm_within_1sigma_per_dim"]) == {"x", "y", "vx", "vy"}
        assert ("replay_error_mean" in m) == (mode == "posterior")  # only recordings replay
    assert math.isfinite(report["posterior"]["skills_2"]["replay_error_median"])
    rows = (data / "reports/validate/error_vs_horizon.csv").read_text().splitlines()
    assert rows[0].startswith("skills,steps,tawm_prior,single_step_prior") and len(rows) == 3
    ends = (data / "reports/validate/end_positions.csv").read_text().splitlines()
    assert len(ends) == 1 + 2 * 2 * 12  # modes x horizons (1 and L) x rollouts
    from rerun.chunk import RrdReader

    entities = set(
        RrdReader(data / "recordings/validate.rrd").stream().collect().schema().entity_paths()
    )
    for path in (
        "/maze/walls",
        "/prior/start_0/real",
        "/posterior/start_0/tawm/sigma2",
        "/prior/start_0/single_step",
    ):
        assert path in entities
    # Beside the rollouts, the data-only section on the same held-out windows.
    assert report["simulated"] and report["recorded"]["starts"] == report["starts"]
    assert report["recorded"]["skills_1"]["tawm_error_mean"] == pytest.approx(
        report["posterior"]["skills_1"]["tawm_recorded_error_mean"], rel=1e-5
    )
    # Same params, same bytes (seeded starts, skills, action noise and particles; no seconds).
    written = data / "reports/validate/report.json"
    before = written.read_bytes()
    again = runner.invoke(app, ["validate", *common, "-S", "validate.record_starts=0"])
    assert again.exit_code == 0, again.output
    assert written.read_bytes() == before


def test_model_from_another_environment_is_a_one_line_error(workdir, tmp_path):
    root, _ = workdir
    data = tmp_path / "data"
    shutil.copytree(root / "data/segments", data / "segments")
    shutil.copytree(root / "data/models", data / "models")
    config = data / "models/tiny/config.json"
    meta = json.loads(config.read_text())
    meta["info"]["env_id"] = "PointMaze_Large-v3"
    config.write_text(json.dumps(meta))
    result = runner.invoke(
        app, ["validate", "--params", str(root / "params.yaml"), "--data", str(data)]
    )
    assert "trained on 'PointMaze_Large-v3'" in _one_line_error(result)


def test_model_option_reads_that_folder_instead(workdir, tmp_path):
    root, common = workdir
    assert (root / "data/models/tiny/by/st_nll_prior/model.safetensors").exists()
    other = tmp_path / "other-model"
    shutil.copytree(root / "data/models/tiny", other)
    meta = json.loads((other / "config.json").read_text())
    meta["info"]["env_id"] = "PointMaze_Large-v3"
    (other / "config.json").write_text(json.dumps(meta))
    result = runner.invoke(app, ["validate", *common, "--model", str(other)])
    assert f"the skill model in {other}" in _one_line_error(result)


def test_dataset_without_test_split_or_with_bad_states_is_a_one_line_error(workdir, tmp_path):
    root, _ = workdir
    segments = load_segments(root / "data/segments/tiny")
    common = ["--params", str(root / "params.yaml"), "--data", str(tmp_path / "data")]
    shutil.copytree(root / "data/models", tmp_path / "data/models")

    segments.episode_split[segments.episode_split == 2] = 0  # test episodes become train
    save_segments(segments, tmp_path / "data/segments/tiny")
    assert "no test split" in _one_line_error(runner.invoke(app, ["validate", *common]))

    segments = load_segments(root / "data/segments/tiny")
    segments.physics[:, 2] += 0.3  # every y off by 0.3 m from its observation
    save_segments(segments, tmp_path / "data/segments/tiny")
    assert "cannot be restored" in _one_line_error(runner.invoke(app, ["validate", *common]))


def test_skill_fidelity_measures_the_replay_against_the_recording(layout):
    """Posterior mode: the executed end vs the recorded end the skill came from, beside the
    TAWM's and no model's distance to that recorded end (hand-made states, known answers)."""
    from pipeline.evaluation.open_loop import ModeResult
    from pipeline.evaluation.open_loop_metrics import horizon_metrics

    b, h = 3, 4
    real = np.zeros((b, h + 1, 4))
    real[:, -1, 0] = 1.0  # every execution ends 1 m along x
    recorded = real.copy()
    recorded[:, -1, 1] = 2.0  # ... and the recording 2 m along y from there
    tawm = recorded[:, None, -1].copy()  # the TAWM predicts the recorded end exactly
    mode = ModeResult(real, np.zeros((b, h, 2)), tawm, tawm, np.ones_like(tawm), real, recorded)
    norm = (np.zeros(4), np.ones(4))
    m = horizon_metrics(mode, 1, h, [0, 1], ["x", "y", "vx", "vy"], norm, np.full(b, 99), layout)
    assert m["replay_error_mean"] == pytest.approx(2.0)
    assert m["tawm_recorded_error_mean"] == pytest.approx(0.0)
    assert m["no_model_recorded_error_median"] == pytest.approx(np.hypot(1.0, 2.0))
    mode.recorded = None
    assert "replay_error_mean" not in horizon_metrics(
        mode, 1, h, [0, 1], ["x", "y", "vx", "vy"], norm, np.full(b, 99), layout
    )
