"""Small real datasets built in memory, and the library's configs built from the params models'
defaults, shared by the tests (`from factories import ...`)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.dataset import DatasetInfo, Episode
from pipeline.errors import UserError


def make_info(name: str = "synthetic", physics_dim: int = 5) -> DatasetInfo:
    return DatasetInfo(
        name=name,
        source="maze",
        env_id="PointMaze_Medium-v3",
        state_names=["x", "y", "vx", "vy"],
        action_names=["fx", "fy"],
        state_units=["m", "m", "m/s", "m/s"],
        action_units=["1", "1"],
        control_period=0.01,
        physics_dim=physics_dim,
        goal_dim=2,
        seed=0,
    )


def make_episodes(lengths: list[int], seed: int = 0, physics_dim: int = 5) -> list[Episode]:
    """Episodes whose states encode (episode, step) so tests can tell where a window came from:
    state[:, 0] = episode index, state[:, 1] = step within the episode."""
    rng = np.random.default_rng(seed)
    episodes, t0 = [], 0.0
    for i, n in enumerate(lengths):
        obs = np.stack([np.full(n, i), np.arange(n), rng.normal(size=n), rng.normal(size=n)], 1)
        episodes.append(
            Episode(
                index=i,
                observations=obs.astype(np.float64),
                actions=rng.uniform(-1, 1, size=(n, 2)),
                time=t0 + 0.01 * np.arange(n),
                physics=rng.normal(size=(n, physics_dim)) if physics_dim else None,
                goals=rng.normal(size=(n, 2)),
                goal_reached=rng.random(n) < 0.01,
            )
        )
        t0 += 0.01 * n
    return episodes


def make_skill_episodes(n_episodes: int, length: int, chunk: int = 10, seed: int = 0):
    """A synthetic skill world: a point whose action is constant for `chunk` steps (a "skill"),
    s = [x, y, vx, vy], x_{t+1} = x_t + 0.05 a_t, v = a_t. Where a window ends depends on the
    actions the skill takes, so a skill model can predict s_T far better than s_T = s_0."""
    rng = np.random.default_rng(seed)
    episodes, t0 = [], 0.0
    for i in range(n_episodes):
        n_chunks = -(-length // chunk)
        directions = rng.uniform(-1, 1, size=(n_chunks, 2))
        actions = np.repeat(directions, chunk, axis=0)[:length]
        actions = actions + 0.05 * rng.normal(size=actions.shape)
        pos = np.cumsum(np.vstack([rng.uniform(-1, 1, size=(1, 2)), 0.05 * actions[:-1]]), 0)
        vel = np.vstack([np.zeros((1, 2)), actions[:-1]])
        episodes.append(
            Episode(
                index=i,
                observations=np.hstack([pos, vel]),
                actions=actions,
                time=t0 + 0.01 * np.arange(length),
            )
        )
        t0 += 0.01 * length
    return episodes


def one_line_error(call) -> str:
    """The message of the `UserError` that `call()` raises, checked to be one line."""
    with pytest.raises(UserError) as err:
        call()
    message = str(err.value)
    assert "\n" not in message
    return message


# The library's configs have no defaults of their own (the params models in `pipeline.config` are
# the one source): these build them from the params models' defaults, the pipeline's, with the
# given params keys changed, through the builders the stages use.


def planner_config(**changes):
    """The skill planner's config of `deploy.planner` (`PlannerParams` keys: horizon, candidates,
    elites, iterations, prior_weight, ...)."""
    from pipeline.config import PlannerParams
    from pipeline.planning.settings import planner_config as build

    return build(PlannerParams(**changes))


def llp_config(**changes):
    """The low-level planner's config of `deploy.llp` (`LLPParams` keys)."""
    from pipeline.config import LLPParams
    from pipeline.planning.settings import llp_config as build

    return build(LLPParams(**changes))


def skill_model_config(state_dim: int, action_dim: int, action_low=None, action_high=None, **train):
    """A skill model's config from `train` (`TrainParams` keys: z_dim, hidden, tawm_shared_std,
    min_std, policy_trunk); `action_low` / `action_high`: censored action bounds."""
    from pipeline.config import TrainParams
    from pipeline.model.settings import skill_model_config as build

    return build(TrainParams(**train), state_dim, action_dim, action_low, action_high)


def small_skill_model():
    """A small skill model (state 4, action 2, z 3, hidden 16) with random weights (seed 0) and
    non-trivial normalization, in eval mode: the planner tests' model."""
    import torch

    from pipeline.model import SkillModel

    torch.manual_seed(0)
    m = SkillModel(skill_model_config(4, 2, z_dim=3, hidden=16))
    m.set_normalization([0.5, -0.5, 0.0, 0.0], [2.0, 2.0, 1.0, 1.0], [0.0, 0.0], [0.5, 0.5])
    return m.eval()


def dynamics_config(state_dim: int, action_dim: int, **changes):
    """The single-step model's config from `dynamics` (`DynamicsParams` keys)."""
    from pipeline.config import DynamicsParams
    from pipeline.model.settings import dynamics_config as build

    return build(DynamicsParams(**changes), state_dim, action_dim)


def policy_config(state_dim: int, action_dim: int, goal_dims=(), **changes):
    """A policy's config from `bc` (`BCParams` keys: hidden, min_std, learned_std)."""
    from pipeline.config import BCParams
    from pipeline.model.settings import policy_config as build

    return build(BCParams(**changes), state_dim, action_dim, goal_dims)


def train_updater(model, **train):
    """The updater `oposm train` builds for `model` from `train` (`TrainParams` keys: method,
    lr_e, lr_m, e_prior, prior_ema, e_kl, dtype, compile, grad_clip)."""
    from pipeline.config import TrainParams
    from pipeline.training.updaters import updater_for

    return updater_for(TrainParams(**train), model)


def kill_an_ingest_while_it_writes(root, name: str):
    """Start `oposm ingest` of a big dataset `name` in `root` (the pipeline's data/demos there),
    SIGKILL it once it is writing, and return the demos folder: what a killed run leaves."""
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    import yaml

    params = Path(root) / "params.yaml"
    params.write_text(
        yaml.safe_dump({"ingest": {"name": name, "episodes": 2000, "episode_steps": 1000}})
    )
    cli = Path(__file__).resolve().parents[1] / "cli.py"
    proc = subprocess.Popen(
        [sys.executable, str(cli), "ingest", "-p", str(params)],
        cwd=root,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    demos = Path(root) / "data" / "demos"

    def written(tmp: Path) -> int:
        try:
            return tmp.stat().st_size if tmp.is_file() else 0
        except FileNotFoundError:  # renamed into place meanwhile
            return 0

    # Midway: a temporary holds data (not merely created), however long the start takes.
    deadline = time.monotonic() + 120
    while proc.poll() is None and time.monotonic() < deadline:
        if any(written(tmp) > 0 for tmp in demos.glob(".tmp-*")):
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert any(demos.glob(".tmp-*")), "the run was killed before it started writing"
    return demos
