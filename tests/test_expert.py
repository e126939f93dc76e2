"""The direction-commanded ant expert: SAC, kill and resume, actor export and loading, check."""

import fcntl
import importlib
import os
import pickle
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from stable_baselines3.common.callbacks import BaseCallback
from typer.testing import CliRunner

from cli import app
from pipeline.ant_expert.actor import load_actor, read_spec, save_actor
from pipeline.ant_expert.check import direction_speed, maze_success
from pipeline.ant_expert.config import AntExpertParams, SACParams, load_expert_params
from pipeline.ant_expert.training import (
    ACTOR_FILE,
    build_sac,
    export_actor,
    resume_dir,
    train_direction_expert,
)
from pipeline.envs.ant import EXPERT_OBS_DIM, UpsideDownEnd, make_direction_env, torso_up
from pipeline.errors import UserError

ROOT = Path(__file__).resolve().parents[1]


def tiny(**changes) -> SACParams:
    base = dict(
        total_steps=150,
        learning_starts=50,
        buffer_size=1000,
        batch_size=16,
        hidden=[16, 16],
        checkpoint_every=50,
        log_every=50,
        max_episode_steps=60,
    )
    return SACParams(**(base | changes))


class _Kill(BaseCallback):
    """Stops the process at `at` steps the hard way: an exception mid-rollout."""

    def __init__(self, at: int) -> None:
        super().__init__()
        self.at = at

    def _on_step(self) -> bool:
        if self.num_timesteps >= self.at:
            raise KeyboardInterrupt
        return True


class _Watch(BaseCallback):
    """Records the step counter and replay size when learning (re)starts."""

    def _on_training_start(self) -> None:
        self.steps = self.num_timesteps
        self.replay = self.model.replay_buffer.size()

    def _on_step(self) -> bool:
        return True


def test_tiny_sac_run_writes_checkpoint_and_actor(tmp_path):
    summary = train_direction_expert(tiny(), tmp_path, info={"command": "test"})
    assert (summary.steps, summary.start_steps, summary.finished) == (150, 0, True)
    state = yaml.safe_load((resume_dir(tmp_path) / "state.json").read_text())
    assert state["steps"] == 150
    spec = read_spec(tmp_path / ACTOR_FILE)
    assert spec.info["steps"] == 150 and spec.info["command"] == "test"
    assert spec.obs_dim == EXPERT_OBS_DIM and spec.action_dim == 8
    assert len((tmp_path / "progress.jsonl").read_text().splitlines()) == 3


def test_killed_run_resumes_from_its_last_checkpoint(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        train_direction_expert(tiny(), tmp_path, callbacks=[_Kill(125)])
    state = yaml.safe_load((resume_dir(tmp_path) / "state.json").read_text())
    assert state["steps"] == 100  # the checkpoint before the kill, not 125
    watch = _Watch()
    summary = train_direction_expert(tiny(), tmp_path, callbacks=[watch])
    assert (watch.steps, watch.replay) == (100, 100)  # step counter and replay buffer restored
    assert (summary.start_steps, summary.steps, summary.finished) == (100, 150, True)
    # More budget continues the same run; other params are refused.
    assert train_direction_expert(tiny(total_steps=170), tmp_path).steps == 170
    with pytest.raises(UserError, match="learning_rate"):
        train_direction_expert(tiny(total_steps=200, learning_rate=3e-4), tmp_path)


class _Record(BaseCallback):
    """The phase's action noise and upside-down end in force at every collected step."""

    def _on_training_start(self) -> None:
        self.seen: list[tuple[int, float]] = []

    def _on_rollout_start(self) -> None:
        self.seen.append((self.num_timesteps, self.model.action_noise.sigma))

    def _on_step(self) -> bool:
        return True


def _phases(*entries):
    return [{"from_step": s, "action_noise": n, "terminate_upside_down": t} for s, n, t in entries]


def test_phases_switch_the_action_noise_at_their_step_and_are_recorded(tmp_path):
    cfg = tiny(phases=_phases((0, 0.0, False), (100, 0.5, True)))
    record = _Record()
    train_direction_expert(cfg, tmp_path, callbacks=[record])
    sigma = dict(record.seen)
    assert sigma[99] == 0.0 and sigma[100] == 0.5 and sigma[149] == 0.5
    state = yaml.safe_load((resume_dir(tmp_path) / "state.json").read_text())
    assert state["phases"] == cfg.model_dump()["phases"]
    progress = [yaml.safe_load(x) for x in (tmp_path / "progress.jsonl").read_text().splitlines()]
    assert [p["action_noise"] for p in progress] == [0.0, 0.0, 0.5]


def test_a_resume_may_add_a_phase_ahead_but_not_change_a_past_one(tmp_path):
    train_direction_expert(tiny(total_steps=100, phases=_phases((0, 0.0, False))), tmp_path)
    with pytest.raises(UserError, match="phases"):
        train_direction_expert(tiny(phases=_phases((0, 0.0, False), (50, 0.2, True))), tmp_path)
    later = tiny(phases=_phases((0, 0.0, False), (100, 0.2, True)))
    assert train_direction_expert(later, tmp_path).steps == 150
    state = yaml.safe_load((resume_dir(tmp_path) / "state.json").read_text())
    assert [p["from_step"] for p in state["phases"]] == [0, 100]


def test_phases_must_start_at_zero_and_increase():
    for bad in (_phases((10, 0.0, False)), _phases((0, 0.0, False), (0, 0.2, True))):
        with pytest.raises(ValueError, match="from_step"):
            tiny(phases=bad)


def test_upside_down_ends_the_episode_only_while_enabled():
    env = UpsideDownEnd(make_direction_env(max_episode_steps=50))
    try:
        for enabled in (False, True):
            env.enabled = enabled
            env.reset(seed=0)
            data = env.unwrapped.data
            data.qpos[3:7] = [0.0, 1.0, 0.0, 0.0]  # rotated 180 degrees about x: upside down
            data.qpos[2] = 0.5
            assert torso_up(data.qpos[3:7]) < 0
            _, _, terminated, _, _ = env.step(np.zeros(8))
            assert terminated == enabled
        assert env.flips == 1
    finally:
        env.close()


def test_a_kill_during_a_checkpoint_write_loses_nothing(tmp_path):
    train_direction_expert(tiny(total_steps=100), tmp_path)
    # Killed between `resume` -> `.old-resume.<pid>` and `.tmp-resume.<x>` -> `resume`:
    resume_dir(tmp_path).rename(tmp_path / ".old-resume.4242")
    (tmp_path / ".tmp-resume.abc").mkdir()
    watch = _Watch()
    assert train_direction_expert(tiny(), tmp_path, callbacks=[watch]).steps == 150
    assert watch.steps == 100
    assert sorted(p.name for p in tmp_path.glob(".*-resume*")) == []


class _Signal(BaseCallback):
    """Sends this process a signal at `at` steps (what `kill PID` or Ctrl-C does)."""

    def __init__(self, at: int, signum: int) -> None:
        super().__init__()
        self.at, self.signum = at, signum

    def _on_step(self) -> bool:
        if self.num_timesteps == self.at:
            os.kill(os.getpid(), self.signum)
        return True


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_sigterm_or_sigint_checkpoints_the_current_step_and_stops(tmp_path, signum):
    handler = signal.getsignal(signum)
    summary = train_direction_expert(tiny(), tmp_path, callbacks=[_Signal(123, signum)])
    assert (summary.steps, summary.finished) == (123, False)
    assert yaml.safe_load((resume_dir(tmp_path) / "state.json").read_text())["steps"] == 123
    watch = _Watch()
    assert train_direction_expert(tiny(), tmp_path, callbacks=[watch]).finished
    assert (watch.steps, watch.replay) == (123, 123)
    assert signal.getsignal(signum) is handler  # restored


def test_one_trainer_per_folder(tmp_path):
    with (tmp_path / ".lock").open("w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        with pytest.raises(UserError, match="another process is training"):
            train_direction_expert(tiny(), tmp_path)


@pytest.mark.slow
def test_sigkill_mid_run_then_the_same_command_resumes(tmp_path):
    """A real SIGKILL of `oposm expert train` (not an exception), then the same command again."""
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump({"sac": tiny(total_steps=800).model_dump()}))
    cmd = [sys.executable, "-m", "cli", "expert", "train", "ant", "-p", str(params)]
    cmd += ["--scratch", str(tmp_path), "--no-ship"]
    env = os.environ | {"OMP_NUM_THREADS": "1"}
    state = tmp_path / "resume" / "state.json"
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not state.exists() or yaml.safe_load(state.read_text())["steps"] < 200:
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    killed_at = yaml.safe_load(state.read_text())["steps"]
    assert 200 <= killed_at < 800
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    assert f"resuming from step {killed_at}" in out.stderr
    assert yaml.safe_load(state.read_text())["steps"] == 800


def test_exported_actor_acts_like_sb3_deterministic_predict(tmp_path):
    cfg = tiny(hidden=[32, 24])
    model = build_sac(cfg, make_direction_env(max_episode_steps=10))
    with torch.no_grad():  # make the weights less regular than the initialisation
        for p in model.policy.actor.parameters():
            p.add_(0.3 * torch.randn_like(p))
    save_actor(export_actor(model, cfg, {"seed": 0}), tmp_path / ACTOR_FILE)
    actor = load_actor(tmp_path / ACTOR_FILE)
    obs = np.random.default_rng(0).normal(0, 3, (64, EXPERT_OBS_DIM))
    expected, _ = model.predict(obs, deterministic=True)
    np.testing.assert_allclose(actor.act(obs), expected, rtol=0, atol=1e-6)
    np.testing.assert_allclose(actor.act(obs[3]), expected[3], rtol=0, atol=1e-6)
    assert np.abs(expected).max() > 0.5  # not a trivially zero policy


def test_loading_needs_neither_sb3_nor_pickle(tmp_path, monkeypatch):
    cfg = tiny()
    model = build_sac(cfg, make_direction_env(max_episode_steps=10))
    save_actor(export_actor(model, cfg, {}), tmp_path / ACTOR_FILE)

    def refuse(*args, **kwargs):
        raise AssertionError("unpickling while loading an actor")

    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(torch, "load", refuse)
    # Re-import our modules with stable_baselines3 made unimportable (monkeypatch restores all).
    monkeypatch.setitem(sys.modules, "stable_baselines3", None)
    for name in [m for m in sys.modules if m == "pipeline" or m.startswith("pipeline.")]:
        monkeypatch.delitem(sys.modules, name)
    fresh = importlib.import_module("pipeline.ant_expert.actor")
    actor = fresh.load_actor(tmp_path / ACTOR_FILE)
    assert actor.act(np.zeros(EXPERT_OBS_DIM)).shape == (8,)


@pytest.mark.slow
def test_a_fresh_process_loads_an_actor_without_importing_sb3(tmp_path):
    cfg = tiny()
    model = build_sac(cfg, make_direction_env(max_episode_steps=10))
    save_actor(export_actor(model, cfg, {}), tmp_path / ACTOR_FILE)
    code = (
        "import sys; from pipeline.ant_expert.actor import load_actor; "
        f"load_actor({str(tmp_path / ACTOR_FILE)!r}); "
        "assert 'stable_baselines3' not in sys.modules, 'loader imported stable_baselines3'"
    )
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True)


def test_missing_or_corrupt_actor_is_a_one_line_user_error(tmp_path):
    cfg = tiny()
    model = build_sac(cfg, make_direction_env(max_episode_steps=10))
    weights = tmp_path / ACTOR_FILE
    save_actor(export_actor(model, cfg, {}), weights)
    meta = weights.with_suffix(".json")
    good_meta, good_weights = meta.read_text(), weights.read_bytes()

    def error(match: str) -> None:
        with pytest.raises(UserError, match=match) as info:
            load_actor(weights)
        assert "\n" not in str(info.value)

    weights.write_bytes(good_weights[:100])
    error("not a readable safetensors file")
    weights.write_bytes(b"")
    error("not a readable safetensors file")
    weights.write_bytes(good_weights)
    meta.write_text(good_meta.replace('"hidden": [\n    16,', '"hidden": [\n    17,'))
    error("do not fit the description")
    meta.write_text("{not json")
    error("not valid JSON")
    meta.write_text('{"format": "something else"}')
    error("not a direction-actor description")
    meta.unlink()
    error("actor description .* not found")
    weights.unlink()
    error("actor weights .* not found")

    result = CliRunner().invoke(app, ["expert", "check", "ant", "--actor", str(weights)])
    assert result.exit_code == 1
    assert result.output.strip().count("\n") == 0 and "not found" in result.output


def test_check_runs_the_speed_and_maze_protocols(tmp_path):
    cfg = tiny()
    actor = export_actor(build_sac(cfg, make_direction_env(max_episode_steps=10)), cfg, {})
    speed = direction_speed(actor, episodes=2, seed=0, max_episode_steps=30)
    assert speed["episodes"] == 2 and speed["episode_steps_mean"] <= 30
    assert speed == direction_speed(actor, episodes=2, seed=0, max_episode_steps=30)
    noisy = direction_speed(actor, episodes=2, seed=0, max_episode_steps=30, action_noise=0.5)
    assert noisy["action_noise"] == 0.5 and noisy["flips"] in (0, 1, 2)
    assert noisy["speed_along_command_mean"] != speed["speed_along_command_mean"]
    maze = maze_success(actor, "antmaze-medium-v0", 1, max_episode_steps=5, seed=0)
    assert [t["task_id"] for t in maze["tasks"]] == [1, 2, 3, 4, 5]
    assert maze["overall"]["episodes"] == 5 and maze["overall"]["successes"] == 0
    assert maze["overall"]["success_ci95_high"] < 0.5


def test_expert_params_file_is_complete_and_matches_the_defaults():
    path = ROOT / "experts" / "ant" / "params.yaml"
    assert load_expert_params(path) == AntExpertParams()
    raw = yaml.safe_load(path.read_text())
    assert set(raw["sac"]) == set(SACParams.model_fields)
    assert set(raw["check"]) == set(AntExpertParams().check.model_dump())
    with pytest.raises(UserError, match="unknown key 'sac.lr'"):
        load_expert_params(path, ["sac.lr=1"])
    result = CliRunner().invoke(app, ["expert", "train", "humanoid"])
    assert result.exit_code == 1 and "unknown robot 'humanoid'" in result.output


def test_cli_trains_checks_and_a_finished_run_ships_its_actor(tmp_path):
    from stages import expert as stage

    params = AntExpertParams(
        sac=tiny(),
        check={
            "speed_episodes": 1,
            "noisy_episodes": 1,
            "mazes": ["antmaze-medium-v0"],
            "episodes_per_task": 1,
            "max_episode_steps": 5,
        },
    )
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params.model_dump()))
    runner = CliRunner()
    args = ["-p", str(path), "--scratch", str(tmp_path)]
    result = runner.invoke(app, ["expert", "train", "ant", *args, "--no-ship"])
    assert result.exit_code == 0, result.output
    actor = tmp_path / ACTOR_FILE
    result = runner.invoke(app, ["expert", "check", "ant", "--actor", str(actor), *args])
    assert result.exit_code == 0, result.output
    assert "antmaze-medium-v0: success 0.0%" in result.output
    assert read_spec(actor).info["quality"]["speed"]["episodes"] == 1

    summary = stage.train(params, "ant", tmp_path / "run", tmp_path / "ship", path)
    shipped = read_spec(tmp_path / "ship" / ACTOR_FILE)
    assert summary["finished"] and summary["shipped"] == str(tmp_path / "ship" / ACTOR_FILE)
    assert shipped.info["steps"] == 150 and shipped.info["seed"] == 0
    assert shipped.info["quality"]["mazes"]["antmaze-medium-v0"]["overall"]["episodes"] == 5
    assert shipped.info["quality"]["actor_steps"] == 150
