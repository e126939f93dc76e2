"""OGBench's manipulation `.npz` files as an ingest source: a small file written the way OGBench's
`data_gen_scripts/generate_manipspace.py` writes one (the installed ogbench env and its oracles,
the script's keys, dtypes and terminals) imports with its states restored, checks, trains; its
statistics match the project's own generator; damaged and foreign files are one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import yaml
from factories import one_line_error
from typer.testing import CliRunner

from cli import app
from pipeline.config import load_params
from pipeline.envs.manipspace.data import check, generate, leaves_table
from pipeline.envs.manipspace.env import READINGS, manipspace_spec
from pipeline.paths import Paths
from pipeline.recording import iter_episodes, read_info
from pipeline.sources.ogbench.manip_npz import (
    load_manipulation_files,
    manipulation_of_file,
    restore_errors,
    write_manipulation_npz,
)
from pipeline.sources.ogbench.manipulation import open_manipulation

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()
CUBE = "cube-single-v0"


# --- a file the way OGBench's script writes it --------------------------------------------------


def _script_oracles(env: gymnasium.Env, env_id: str, dataset_type: str) -> dict:
    """The script's agents: plan oracles (noise 0.1, smoothing 0.5) for play, Markov oracles
    (min_norm 0.4; the scene's cube one with max_step 100) for noisy; a puzzle's button oracle
    with the gripper always closed."""
    from ogbench.manipspace.oracles.markov import button_markov, cube_markov, drawer_markov
    from ogbench.manipspace.oracles.markov import window_markov as window_m
    from ogbench.manipspace.oracles.plan import button_plan, cube_plan, drawer_plan, window_plan

    if env_id.startswith("puzzle-"):
        if dataset_type == "play":
            oracle = button_plan.ButtonPlanOracle(
                env=env, noise=0.1, noise_smoothing=0.5, gripper_always_closed=True
            )
        else:
            oracle = button_markov.ButtonMarkovOracle(
                env=env, min_norm=0.4, gripper_always_closed=True
            )
        return {"button": oracle}
    kinds = ("cube", "button", "drawer", "window") if env_id == "scene-v0" else ("cube",)
    if dataset_type == "play":
        plans = (cube_plan.CubePlanOracle, button_plan.ButtonPlanOracle,
                 drawer_plan.DrawerPlanOracle, window_plan.WindowPlanOracle)  # fmt: skip
        made = dict(zip(("cube", "button", "drawer", "window"), plans, strict=True))
        return {k: made[k](env=env, noise=0.1, noise_smoothing=0.5) for k in kinds}
    markovs = (cube_markov.CubeMarkovOracle, button_markov.ButtonMarkovOracle,
               drawer_markov.DrawerMarkovOracle, window_m.WindowMarkovOracle)  # fmt: skip
    made = dict(zip(("cube", "button", "drawer", "window"), markovs, strict=True))
    agents = {k: made[k](env=env, min_norm=0.4) for k in kinds}
    if env_id == "scene-v0":
        agents["cube"] = cube_markov.CubeMarkovOracle(env=env, min_norm=0.4, max_step=100)
    return agents


def write_like_ogbench(
    path: Path, env_id: str, dataset_type: str, episodes: int, val: int, steps: int, seed: int
) -> dict:
    """`episodes` (+ `val` in the `-val.npz`) episodes of `steps` steps, collected and saved as
    OGBench's script does: a `data_collection` env without goal termination truncated at
    `steps`, one oracle per subtask kind, a new subtask when the oracle is done, the state before
    each step from `info['prev_qpos']` etc., float32 / bool / int64 arrays, `savez_compressed`.
    Seeded here (the script is not). Returns the subtasks the oracle finished per episode and
    the env's exact states (`state_of_env`) before each step, per episode."""
    import ogbench.manipspace  # noqa: F401  (registers the ids)

    np.random.seed(seed)
    env = gymnasium.make(
        env_id, terminate_at_goal=False, mode="data_collection", max_episode_steps=steps
    )
    env.reset(seed=seed)
    spec = manipspace_spec(env_id)
    agents = _script_oracles(env, env_id, dataset_type)
    p_random = 0.0 if dataset_type == "play" else 0.2 if env_id.startswith("puzzle-") else 0.1
    rows: dict[str, list] = {k: [] for k in ("observations", "actions", "terminals", "qpos",
                                             "qvel", "button_states")}  # fmt: skip
    exact, finished = [], []
    for _ in range(episodes + val):
        while True:
            start = {k: len(v) for k, v in rows.items()}
            ob, info = env.reset()
            p_stack = {"cube-single-v0": 0.0, "cube-double-v0": np.random.uniform(0.0, 0.25)}
            p_stack = p_stack.get(env_id, 0.5)
            xi = np.random.uniform(0, 0.1) if dataset_type == "noisy" else 0.0
            agent = agents[info["privileged/target_task"]]
            agent.reset(ob, info)
            done, done_here, states = False, 0, []
            while not done:
                states.append(spec.state_of_env(env))
                if np.random.rand() < p_random:
                    action = env.action_space.sample()
                else:
                    action = np.array(agent.select_action(ob, info))
                    if dataset_type == "noisy":
                        action = action + np.random.normal(0, xi * np.array([1, 1, 1, 3, 10]))
                action = np.clip(action, -1, 1)
                next_ob, _, terminated, truncated, info = env.step(action)
                done = terminated or truncated
                if agent.done:
                    done_here += 1
                    agent_ob, agent_info = env.unwrapped.set_new_target(p_stack=p_stack)
                    agent = agents[agent_info["privileged/target_task"]]
                    agent.reset(agent_ob, agent_info)
                rows["observations"].append(ob)
                rows["actions"].append(action)
                rows["terminals"].append(done)
                rows["qpos"].append(info["prev_qpos"])
                rows["qvel"].append(info["prev_qvel"])
                if "prev_button_states" in info:
                    rows["button_states"].append(info["prev_button_states"])
                ob = next_ob
            qpos = np.array(rows["qpos"][start["qpos"] :])
            if env_id == "scene-v0" and leaves_table(qpos[:, None, 14:17]):
                for k, v in rows.items():  # the script's health rule: redo the episode
                    del v[start[k] :]
                continue
            exact.append(np.array(states))
            finished.append(done_here)
            break
    dtypes = {"terminals": bool, "button_states": np.int64}
    split = episodes * steps
    for target, part in ((path, slice(0, split)), (_val(path), slice(split, None))):
        arrays = {k: np.array(v[part], dtype=dtypes.get(k, np.float32)) for k, v in rows.items()
                  if v}  # fmt: skip
        np.savez_compressed(target, **arrays)
    return {"finished_per_episode": np.array(finished), "exact": exact}


def _val(path: Path) -> Path:
    return path.with_name(path.stem + "-val.npz")


def episode_statistics(observations: np.ndarray, actions: np.ndarray, steps: int) -> dict:
    """Per episode of `steps` steps, per dim: `[E, D]` means and stds of observations and
    actions, and `[E]` cube lifts per 1000 steps (the cube's z rising past 0.05 m: what a file
    shows of the oracle's subtasks, one lift each in cube-single)."""
    obs = observations.reshape(-1, steps, observations.shape[-1])
    act = actions.reshape(-1, steps, actions.shape[-1])
    lifted = obs[:, :, CUBE_Z] > LIFTED
    lifts = (lifted[:, 1:] & ~lifted[:, :-1]).sum(axis=1)
    return {
        "obs_mean": obs.mean(1),
        "obs_std": obs.std(1),
        "act_mean": act.mean(1),
        "act_std": act.std(1),
        "lifts_per_1000": 1000.0 * lifts / steps,
    }


def z_scores(a: np.ndarray, b: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """`[D]` gap of two samples' means `[E_a, D]`, `[E_b, D]` in standard errors (episodes as
    the independent units: steps within one are strongly correlated); `floor` keeps dims that
    hardly vary between episodes from dividing by ~0."""
    se = np.sqrt(a.var(0, ddof=1) / len(a) + b.var(0, ddof=1) / len(b) + floor**2)
    return np.abs(a.mean(0) - b.mean(0)) / se


CUBE_Z = 21  # cube0_z in observation units (10 x m)
LIFTED = 0.5  # 0.05 m: the cube rests at 0.02 m


@pytest.fixture(scope="module")
def script_file(tmp_path_factory):
    """cube-single play: 4 episodes of 120 steps and a 1-episode `-val.npz`."""
    path = tmp_path_factory.mktemp("ogbench") / "cube-single-play-v0.npz"
    made = write_like_ogbench(path, CUBE, "play", episodes=4, val=1, steps=120, seed=3)
    return path, made


# --- import, check, train ----------------------------------------------------------------------

TINY = [
    "ingest.name=og",
    "segment.window=6",
    "train.z_dim=4",
    "train.hidden=16",
    "train.max_steps=20",
    "train.eval_every=10",
    "train.checkpoint_every=10",
    "train.batch_size=8",
    "train.val_windows=8",
    "train.threads=1",
]


def test_the_script_writes_what_ogbenchs_files_hold(script_file):
    path, made = script_file
    with np.load(path) as f:
        assert {k: (f[k].dtype, f[k].shape) for k in f.files} == {
            "observations": (np.float32, (480, 28)),
            "actions": (np.float32, (480, 5)),
            "terminals": (np.bool_, (480,)),
            "qpos": (np.float32, (480, 21)),
            "qvel": (np.float32, (480, 20)),
        }
        assert np.flatnonzero(f["terminals"]).tolist() == [119, 239, 359, 479]
    assert manipulation_of_file(path) == (CUBE, "play")
    assert manipulation_of_file(_val(path)) == (CUBE, "play")
    assert manipulation_of_file(path.with_name("puzzle-4x6-noisy-v0.npz")) == (
        "puzzle-4x6-v0",
        "noisy",
    )
    assert made["finished_per_episode"].sum() >= 3  # a subtask takes the plan oracle ~100 steps


def test_an_ogbench_file_imports_restored_checks_and_trains(script_file, tmp_path):
    """The CLI's ingest of the file and its -val: five episodes, states within float32 of the
    env's own (the readings within 1e-6 m), the restore gaps in the report; segment and 20 EM
    steps train on it."""
    from stages import ingest, segment, train

    path, made = script_file
    params = load_params(
        ROOT / "params-ogbench-cube-single-play.yaml",
        [*TINY, f"ingest.ogbench.path={path}"],
    )
    paths = Paths(tmp_path / "data")
    report = ingest.run(params, paths, progress=False)
    assert (report["episodes"], report["steps"], report["n_problems"]) == (5, 600, 0)
    assert report["restore_observation_error_max"] < 1e-5  # float32 rounding
    assert report["restore_next_error_mean"] < 1e-3  # measured ~3e-5
    assert report["restore_next_error_max"] < 0.05  # measured ~4e-3 on OGBench's own file
    assert report["restore_steps"] == 5  # step 0 of each episode (every 200th)
    assert "goals_reached" not in report  # the file does not say when subtasks ended
    info = read_info(paths.demos("og"))
    spec = manipspace_spec(CUBE)
    assert (info.env_id, info.physics_dim, info.seed) == (CUBE, spec.physics_dim, None)
    assert info.generator["dataset_type"] == "play"
    assert [f["episodes"] for f in info.generator["files"]] == [4, 1]
    nq, nv = spec.model.nq, spec.model.nv
    for ep, exact in zip(iter_episodes(paths.demos("og")), made["exact"], strict=True):
        state = slice(1, 1 + nq + nv)
        assert np.array_equal(ep.physics[:, state], exact[:, state].astype(np.float32))
        assert np.all(ep.physics[:, 1 + nq + nv : 1 + nq + 2 * nv] == 0)  # warm start
        pinch = slice(1 + nq + 2 * nv, 4 + nq + 2 * nv)
        assert np.abs(ep.physics[:, pinch] - exact[:, pinch]).max() < 1e-6  # m
        assert ep.terminals[-1] and not ep.terminals[:-1].any()
    segment.run(params, paths)
    train.run(params, paths)
    metrics = json.loads((paths.root / "reports/train/metrics.json").read_text())
    assert metrics["step"] == 20 and np.isfinite(metrics["val"]["st_nll_prior"])


def test_generated_episodes_round_trip_through_ogbenchs_layout(tmp_path):
    """The generator's scene episodes written as OGBench's file and imported: arrays as stored,
    button states kept, every restored state observing its recorded observation to float32
    rounding, and one step from it landing near the recorded next one."""
    exact = list(open_manipulation("scene-v0", "play", 2, 30, 5, "g").episodes)
    path = tmp_path / "scene-play-v0.npz"
    assert write_manipulation_npz(path, exact, "scene-v0") == 60
    with np.load(path) as f:
        assert f["button_states"].dtype == np.int64 and f["button_states"].shape == (60, 2)
        assert f["terminals"].dtype == np.bool_ and f["observations"].dtype == np.float32
    imported = list(open_manipulation("scene-v0", "navigate", 1, 1, 0, "i", path=path).episodes)
    spec = manipspace_spec("scene-v0")
    buttons = 1 + spec.model.nq + 2 * spec.model.nv + READINGS
    for got, want in zip(imported, exact, strict=True):
        assert np.array_equal(got.observations, want.observations.astype(np.float32))
        assert np.array_equal(got.physics[:, buttons:], want.physics[:, buttons:])
        assert np.array_equal(got.time, want.time)
        qpos = slice(1, 1 + spec.model.nq)
        assert np.array_equal(got.physics[:, qpos], want.physics[:, qpos].astype(np.float32))
        own, after = restore_errors(spec, got, every=1, step_every=1)
        assert own.max() < 1e-5 and after.mean() < 1e-3, (own.max(), after.mean())


# --- the puzzles ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def puzzle_file(tmp_path_factory):
    """puzzle-3x3 play as OGBench's script writes it: 2 episodes of 150 steps and a 1-episode
    `-val.npz`."""
    path = tmp_path_factory.mktemp("ogbench") / "puzzle-3x3-play-v0.npz"
    made = write_like_ogbench(path, "puzzle-3x3-v0", "play", episodes=2, val=1, steps=150, seed=4)
    return path, made


def test_a_puzzle_file_imports_with_its_button_states_through_ingest(puzzle_file, tmp_path):
    """`ingest.ogbench.path` of OGBench's puzzle file and its -val: three episodes, each step's
    button states as the file holds them (and as the env had them), qpos and qvel its float32,
    the restored states observing their observations to float32 rounding; the presses it
    recorded flip a button and its neighbours."""
    from stages import ingest

    path, made = puzzle_file
    with np.load(path) as f:
        assert f["button_states"].dtype == np.int64 and f["button_states"].shape == (300, 9)
        assert f["observations"].shape == (300, 55) and f["qpos"].shape[1] == 23
    params = load_params(
        ROOT / "params-ogbench-puzzle-3x3-play.yaml",
        ["ingest.name=og", f"ingest.ogbench.path={path}"],
    )
    paths = Paths(tmp_path / "data")
    report = ingest.run(params, paths, progress=False)
    assert (report["episodes"], report["steps"], report["n_problems"]) == (3, 450, 0)
    assert report["restore_observation_error_max"] < 1e-5
    assert report["restore_next_error_max"] < 0.05
    spec = manipspace_spec("puzzle-3x3-v0")
    info = read_info(paths.demos("og"))
    assert (info.env_id, info.physics_dim, info.generator["dataset_type"]) == (
        "puzzle-3x3-v0", spec.physics_dim, "play")  # fmt: skip
    assert info.state_names[19:23] == ["button0_off", "button0_on", "button0_pos", "button0_vel"]
    nq, nv = spec.model.nq, spec.model.nv
    buttons = 1 + nq + 2 * nv + READINGS
    flips = 0
    for ep, exact in zip(iter_episodes(paths.demos("og")), made["exact"], strict=True):
        assert np.array_equal(ep.physics[:, buttons:], exact[:, buttons:])  # the env's states
        assert np.array_equal(ep.physics[:, 1 : 1 + nq], exact[:, 1 : 1 + nq].astype(np.float32))
        changed = np.abs(np.diff(ep.physics[:, buttons:], axis=0)).sum(axis=1)
        flips += int((changed >= 2).sum())  # a press with its neighbours
    assert flips >= 2 and made["finished_per_episode"].sum() >= 2


def test_generated_puzzle_episodes_round_trip_through_ogbenchs_layout(tmp_path):
    """The generator's puzzle-4x4 noisy episodes written in OGBench's layout (16 button states
    per step) and imported back: the button states and observations as stored."""
    exact = list(open_manipulation("puzzle-4x4-v0", "noisy", 2, 40, 2, "g").episodes)
    path = tmp_path / "puzzle-4x4-noisy-v0.npz"
    assert write_manipulation_npz(path, exact, "puzzle-4x4-v0") == 80
    with np.load(path) as f:
        assert f["button_states"].dtype == np.int64 and f["button_states"].shape == (80, 16)
    imported = list(open_manipulation("puzzle-4x4-v0", "play", 1, 1, 0, "i", path=path).episodes)
    spec = manipspace_spec("puzzle-4x4-v0")
    buttons = 1 + spec.model.nq + 2 * spec.model.nv + READINGS
    for got, want in zip(imported, exact, strict=True):
        assert np.array_equal(got.observations, want.observations.astype(np.float32))
        assert np.array_equal(got.physics[:, buttons:], want.physics[:, buttons:])
        own, after = restore_errors(spec, got, every=1, step_every=1)
        # measured: median ~5e-7; one step in which the gripper touches a button, 0.087 (the
        # button's position x 120: 0.7 mm), as the cube files' rare contact steps
        assert own.max() < 1e-5 and np.median(after) < 1e-5 and after.max() < 0.2, (
            own.max(), np.median(after), after.max())  # fmt: skip


# --- the project's generator against the script --------------------------------------------------


@pytest.mark.slow
def test_the_generator_makes_what_the_script_makes():
    """cube-single play, 6 episodes x 300 steps each way (different seeds): per dim, the
    action and observation means and stds, the oracle's subtasks per 1000 steps and the cube
    lifts per 1000 steps agree within 5 standard errors over episodes (floors: 2 % of the
    dims' spread, a Poisson rate's error). Measured: at most 3.1 (observation stds); our
    generator's noisy data against this play file: 8.8 (observation stds), 10.9 (action means),
    22.8 (action stds), 8.7 (lifts)."""
    import tempfile

    steps = 300
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "cube-single-play-v0.npz"
        script = write_like_ogbench(path, CUBE, "play", episodes=6, val=0, steps=steps, seed=11)
        with np.load(path) as f:
            theirs = episode_statistics(f["observations"], f["actions"], steps)
    ours_eps = generate(CUBE, "play", episodes=6, episode_steps=steps, seed=12)
    ours = episode_statistics(
        np.concatenate([e["observations"][:-1] for e in ours_eps]),
        np.concatenate([e["actions"] for e in ours_eps]),
        steps,
    )
    per_episode = check(ours_eps, manipspace_spec(CUBE))["per_episode"]
    ours["subtasks_per_1000"] = np.array([1000.0 * p["finished"] / steps for p in per_episode])
    theirs["subtasks_per_1000"] = 1000.0 * script["finished_per_episode"] / steps
    for key, a in theirs.items():
        b = ours[key]
        if key.endswith("_per_1000"):  # counts: at least a pooled Poisson rate's error
            floor = np.sqrt(np.mean([a.mean(), b.mean()]) * 1000 / (steps * len(a)))
        else:
            floor = 0.02 * a.std(0).mean()
        z = z_scores(a.reshape(len(a), -1), b.reshape(len(b), -1), floor)
        assert z.max() < 5.0, (key, z.round(1))


# --- bad files ---------------------------------------------------------------------------------


def _open(path: Path, env_id: str = CUBE):
    return open_manipulation(env_id, "play", 1, 1, 0, "x", path=path)


def test_damaged_foreign_and_mismatched_files_are_one_line_errors(script_file, tmp_path):
    path, _ = script_file
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}

    def save(name: str, **changes) -> Path:
        out = tmp_path / name
        kept = {k: v for k, v in {**arrays, **changes}.items() if v is not None}
        np.savez_compressed(out, **kept)
        return out

    damaged = tmp_path / "cube-single-play-v0.npz"
    damaged.write_bytes(path.read_bytes()[:2000])  # truncated download
    assert "damaged or truncated" in one_line_error(lambda: _open(damaged))
    text = tmp_path / "notes.npz"
    text.write_text("not a zip")
    assert "not a .npz" in one_line_error(lambda: _open(text))
    assert "not found" in one_line_error(lambda: _open(tmp_path / "nope.npz"))
    message = one_line_error(lambda: _open(save("cube-double-play-v0.npz")))
    assert "set ingest.ogbench.env_id=cube-double-v0" in message  # the name says another env
    message = one_line_error(lambda: _open(save("cube-triple-play-v0.npz")))
    assert "not simulated here" in message and "cube-triple-v0" in message
    message = one_line_error(lambda: _open(save("puzzle-3x3-play-v0.npz")))
    assert "set ingest.ogbench.env_id=puzzle-3x3-v0" in message  # a puzzle file: simulated
    message = one_line_error(lambda: _open(save("pointmaze-medium-navigate-v0.npz")))
    assert "set ingest.ogbench.env_id=pointmaze-medium-v0" in message
    message = one_line_error(lambda: _open(save("visual-cube-single-play-v0.npz")))
    assert "cube-single-play-v0.npz" in message and "images" in message
    message = one_line_error(lambda: _open(save("noqpos.npz", qpos=None)))
    assert "noqpos.npz" in message and "'qpos'" in message and "actions" in message
    wide = np.concatenate([arrays["observations"], np.zeros((480, 9), np.float32)], axis=1)
    message = one_line_error(lambda: _open(save("wide.npz", observations=wide)))
    assert "`observations` has 37 values per step, cube-single-v0 has 28" in message
    message = one_line_error(lambda: _open(save("short.npz", actions=arrays["actions"][:5])))
    assert "different lengths" in message
    shuffled = np.roll(arrays["qpos"], 7, axis=0)  # sizes fit, states do not
    message = one_line_error(lambda: _open(save("foreign.npz", qpos=shuffled)))
    assert "foreign.npz" in message and "not an OGBench cube-single-v0 file" in message
    # the scene and the puzzles need their button states
    message = one_line_error(lambda: _open(save("scene.npz"), "scene-v0"))
    assert "'button_states'" in message
    message = one_line_error(lambda: _open(save("puzzle.npz"), "puzzle-4x4-v0"))
    assert "'button_states'" in message


def test_the_cli_ingest_of_a_bad_file_is_one_line_and_leaves_nothing(script_file, tmp_path):
    path, _ = script_file
    bad = tmp_path / "cube-single-play-v0.npz"
    bad.write_bytes(path.read_bytes()[:2000])
    params = {"extends": str(ROOT / "params-ogbench-cube-single-play.yaml"),
              "ingest": {"name": "bad", "ogbench": {"path": str(bad)}}}  # fmt: skip
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    args = ["ingest", "--params", str(tmp_path / "params.yaml"), "--data", str(tmp_path / "data")]
    result = runner.invoke(app, args)
    assert result.exit_code == 1
    assert len(result.stderr.strip().splitlines()) == 1 and str(bad) in result.stderr
    assert not (tmp_path / "data/demos/bad.mcap").exists()


def test_an_empty_val_companion_is_skipped(script_file, tmp_path):
    """OGBench's script writes an empty -val.npz for fewer than 10 episodes."""
    path, _ = script_file
    copy = tmp_path / path.name
    copy.write_bytes(path.read_bytes())
    with np.load(path) as f:
        np.savez_compressed(_val(copy), **{k: f[k][:0] for k in f.files})
    _, files, loaded = load_manipulation_files(copy, CUBE, include_val=True)
    assert files == [copy] and len(loaded) == 1
