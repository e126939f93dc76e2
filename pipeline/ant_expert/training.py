"""SAC training of the direction-commanded ant expert (OGBench's recipe), resumable after a kill.

stable-baselines3 does the SAC; this module builds it with OGBench's settings, checkpoints it into a
resume folder every `checkpoint_every` steps, continues from the last checkpoint after a kill (same
step counter, replay buffer restored), and exports the actor as safetensors + JSON.

The resume folder (`<out>/resume/`: `sac.zip`, `replay.pkl`, `state.json`) holds stable-baselines3's
own `save` / `save_replay_buffer` files, which are pickles: they are written and read only by this
module, never shipped and never read from a user. What leaves training is the actor export, which
`pipeline.ant_expert.actor` reads without stable-baselines3 or pickle.

A checkpoint is taken between two rollouts (after the step's gradient update), so it holds exactly
`steps` transitions and their updates. A resumed run starts a new episode (the simulator's mid-
episode state is not saved) and reseeds with `seed + steps`: it continues the same run, but is not
bit-identical to one that was never interrupted.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import shutil
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict
from stable_baselines3 import SAC
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import ActionNoise
from torch import nn
from tqdm import tqdm

from pipeline.ant_expert.actor import ActorSpec, DirectionActor, save_actor
from pipeline.ant_expert.config import SACParams, SACPhase
from pipeline.devices import resolve_device
from pipeline.envs.ant import UpsideDownEnd, make_direction_env
from pipeline.errors import UserError
from pipeline.io import atomic_dir
from pipeline.readback import READBACK_CONFIG, Count, read_json, validated

log = logging.getLogger(__name__)

_ACTIVATIONS: dict[str, type[nn.Module]] = {"gelu": nn.GELU, "relu": nn.ReLU}
# Params that change how long or where a run goes, not what it computes: a resume may change them.
_BUDGET_KEYS = {"total_steps", "checkpoint_every", "log_every", "threads", "device"}
# Checked on their own: a resume may add phases that have not started yet (`_past_phases`).
_PHASES = "phases"
_MODEL, _REPLAY, _STATE = "sac.zip", "replay.pkl", "state.json"
ACTOR_FILE = "actor.safetensors"


@dataclass
class TrainSummary:
    """How a `train_direction_expert` call went."""

    steps: int
    """Environment steps done in total (over all resumed runs)."""
    start_steps: int
    """Steps already done when this call started (0: a fresh run)."""
    finished: bool
    """`steps` reached `total_steps`."""
    seconds: float
    """Wall time of this call."""
    steps_per_s: float
    """Throughput of this call (environment steps, with their updates)."""


def resume_dir(out: Path) -> Path:
    return out / "resume"


def build_sac(cfg: SACParams, env: Any) -> SAC:
    """A fresh stable-baselines3 SAC with OGBench's ant-expert settings."""
    action_dim = env.action_space.shape[0]
    return SAC(
        "MlpPolicy",
        env,
        learning_rate=cfg.learning_rate,
        buffer_size=cfg.buffer_size,
        learning_starts=cfg.learning_starts,
        batch_size=cfg.batch_size,
        tau=cfg.tau,
        gamma=cfg.gamma,
        train_freq=cfg.train_freq,
        gradient_steps=cfg.gradient_steps,
        target_entropy=-cfg.target_entropy_per_dim * action_dim,
        policy_kwargs={"net_arch": list(cfg.hidden), "activation_fn": _ACTIVATIONS[cfg.activation]},
        seed=cfg.seed,
        device=resolve_device(cfg.device, "sac.device"),
        verbose=0,
    )


def export_actor(model: SAC, cfg: SACParams, info: dict[str, Any]) -> DirectionActor:
    """Copy SAC's actor (trunk, mean and log-std heads) into a plain `DirectionActor`."""
    space = model.action_space
    spec = ActorSpec(
        obs_dim=int(model.observation_space.shape[0]),
        action_dim=int(space.shape[0]),
        hidden=list(cfg.hidden),
        activation=cfg.activation,
        action_low=[float(x) for x in space.low],
        action_high=[float(x) for x in space.high],
        info=info,
    )
    actor = DirectionActor(spec)
    sb3 = model.policy.actor.state_dict()
    state = {k.replace("latent_pi.", "trunk."): v for k, v in sb3.items() if "latent_pi." in k}
    state |= {k: v for k, v in sb3.items() if k.startswith(("mu.", "log_std."))}
    actor.load_state_dict({k: v.detach().cpu() for k, v in state.items()}, strict=False)
    return actor.eval()


def _fingerprint(cfg: SACParams) -> dict[str, Any]:
    return cfg.model_dump(exclude=_BUDGET_KEYS | {_PHASES})


def _past_phases(phases: list[dict[str, Any]], steps: int) -> list[dict[str, Any]]:
    """The phases that collected some of the first `steps` environment steps."""
    return [p for p in phases if p["from_step"] < steps]


class _PhaseNoise(ActionNoise):
    """Gaussian action noise whose std the current phase sets (no draw while it is 0).

    stable-baselines3 hands `model.action_noise` to each rollout before the rollout's callbacks
    run, so the phase changes this object's `sigma` rather than replacing it.
    """

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim, self.sigma = dim, 0.0

    def __call__(self) -> np.ndarray:
        if self.sigma == 0.0:
            return np.zeros(self.dim)
        return np.random.normal(0.0, self.sigma, size=self.dim)


class _Checkpointer(BaseCallback):
    """Progress bar, progress log, and checkpoints between rollouts (after the step's update)."""

    def __init__(
        self,
        cfg: SACParams,
        out: Path,
        info: dict[str, Any],
        start: int,
        flips: UpsideDownEnd,
        noise: _PhaseNoise,
    ) -> None:
        super().__init__()
        self.cfg, self.out, self.info = cfg, out, info
        self.flips, self.noise = flips, noise
        self.phase: SACPhase | None = None
        self.last_checkpoint = start
        self.last_log = start
        self.start = start
        self.t0 = time.monotonic()
        self.rewards: deque[float] = deque(maxlen=cfg.log_every)
        self.bar: tqdm | None = None
        self.dt = 1.0
        self.stop_signal: int | None = None

    def _apply_phase(self) -> None:
        """Action noise and the upside-down end of the phase that collects the next step."""
        phase = self.cfg.phase_at(self.num_timesteps)
        if phase == self.phase:
            return
        self.noise.sigma = phase.action_noise
        self.flips.enabled = phase.terminate_upside_down
        self.phase = phase
        log.info("step %d: phase %s", self.num_timesteps, phase.model_dump())

    def _on_training_start(self) -> None:
        self._apply_phase()
        self.dt = float(self.training_env.envs[0].unwrapped.dt)
        tty = sys.stderr.isatty()
        self.bar = tqdm(
            total=self.cfg.total_steps,
            initial=self.num_timesteps,
            desc="sac ant",
            unit="step",
            mininterval=1.0 if tty else 60.0,
            dynamic_ncols=True,
        )

    def _on_step(self) -> bool:
        self.rewards.extend(float(r) for r in self.locals["rewards"])
        if self.bar is not None:
            self.bar.update(1)
        if self.num_timesteps - self.last_log >= self.cfg.log_every:
            self._log()
        return True

    def _on_rollout_start(self) -> None:
        if self.stop_signal is not None:
            if self.num_timesteps > self.last_checkpoint:
                self.save()
            if self.bar is not None:
                self.bar.close()
            raise _Stopped(self.stop_signal)
        if self.num_timesteps - self.last_checkpoint >= self.cfg.checkpoint_every:
            self.save()
        self._apply_phase()

    def _on_training_end(self) -> None:
        if self.num_timesteps > self.last_checkpoint:
            self.save()
        if self.bar is not None:
            self.bar.close()

    def metrics(self) -> dict[str, float | str]:
        episodes = list(self.model.ep_info_buffer or [])
        elapsed = time.monotonic() - self.t0
        return {
            "step": self.num_timesteps,
            "speed_along_command": float(np.mean(self.rewards)) / self.dt if self.rewards else 0.0,
            "episode_return_mean": float(np.mean([e["r"] for e in episodes])) if episodes else 0.0,
            "episode_length_mean": float(np.mean([e["l"] for e in episodes])) if episodes else 0.0,
            "ent_coef": float(torch.exp(self.model.log_ent_coef.detach()).item()),
            "action_noise": self.phase.action_noise if self.phase else 0.0,
            "upside_down_ends": self.flips.flips,  # since this process started
            "steps_per_s": (self.num_timesteps - self.start) / elapsed if elapsed > 0 else 0.0,
            "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }

    def _log(self) -> None:
        self.last_log = self.num_timesteps
        m = self.metrics()
        if self.bar is not None:
            self.bar.set_postfix(
                speed=f"{m['speed_along_command']:.2f}", ep_len=f"{m['episode_length_mean']:.0f}"
            )
        with (self.out / "progress.jsonl").open("a") as f:
            f.write(json.dumps(m) + "\n")

    def save(self) -> None:
        """Write the resume folder as a whole (atomically) and export the actor beside it."""
        steps = self.num_timesteps
        with atomic_dir(resume_dir(self.out)) as tmp:
            self.model.save(tmp / _MODEL)
            self.model.save_replay_buffer(tmp / _REPLAY)
            state = {
                "steps": steps,
                "sac": _fingerprint(self.cfg),
                _PHASES: _past_phases(self.cfg.model_dump()[_PHASES], steps),
                "metrics": self.metrics(),
            }
            (tmp / _STATE).write_text(json.dumps(state, indent=2) + "\n")
        info = {**self.info, "steps": steps, "metrics_at_export": self.metrics()}
        save_actor(export_actor(self.model, self.cfg, info), self.out / ACTOR_FILE)
        self.last_checkpoint = steps
        log.info("checkpoint at step %d in %s", steps, resume_dir(self.out))


class _Stopped(Exception):
    """A stop was requested by a signal; the checkpoint of the current step is written."""


@contextlib.contextmanager
def _checkpoint_on_signals(checkpointer: _Checkpointer) -> Iterator[None]:
    """SIGTERM or SIGINT: finish the step, checkpoint it and stop, instead of losing up to
    `checkpoint_every` steps (SIGKILL still loses them; the previous checkpoint stays valid)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def request(signum: int, frame: Any) -> None:
        checkpointer.stop_signal = signum

    previous = {s: signal.signal(s, request) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


class _SavedPhase(BaseModel):
    model_config = ConfigDict(extra="allow")  # the rest of the phase, compared as written
    from_step: Count


class _SavedState(BaseModel):
    """The resume folder's state.json, as `_load` reads it back."""

    model_config = READBACK_CONFIG
    steps: Count
    sac: dict[str, Any]
    phases: list[_SavedPhase] | None = None


def _load(cfg: SACParams, env: Any, folder: Path) -> SAC:
    """SAC and replay buffer from a resume folder written with the same (non-budget) params."""
    path, fix = folder / _STATE, f"delete {folder} to start afresh"
    state = validated(_SavedState, read_json(path, fix), path, fix).model_dump()
    if state.get("sac") != _fingerprint(cfg):
        changed = sorted(
            k for k, v in _fingerprint(cfg).items() if state.get("sac", {}).get(k) != v
        )
        raise UserError(
            f"{folder} was written with other sac params ({', '.join(changed)} differ); "
            f"restore them, or delete {folder} to start afresh"
        )
    steps = int(state["steps"])
    # written before phases existed: one phase, no noise, no upside-down end
    saved = state[_PHASES] if state[_PHASES] is not None else [SACPhase().model_dump()]
    done = _past_phases(saved, steps)
    if done != _past_phases(cfg.model_dump()[_PHASES], steps):
        raise UserError(
            f"{folder} is at step {steps}, collected with sac.phases {done}; a resumed run may "
            f"only add phases from step {steps} on; restore them, or delete {folder}"
        )
    device = resolve_device(cfg.device, "sac.device")
    model = SAC.load(folder / _MODEL, env=env, device=device, force_reset=True)
    model.load_replay_buffer(folder / _REPLAY)
    if model.num_timesteps != state["steps"]:
        raise UserError(f"{folder}: model at step {model.num_timesteps}, state {state['steps']}")
    model.set_random_seed(cfg.seed + model.num_timesteps)
    return model


def train_direction_expert(
    cfg: SACParams,
    out: str | Path,
    info: dict[str, Any] | None = None,
    callbacks: Sequence[BaseCallback] = (),
) -> TrainSummary:
    """Train (or resume) SAC on the ant direction task up to `cfg.total_steps` steps.

    Args:
        cfg: SAC and task params.
        out: scratch folder: `resume/` (checkpoints), `actor.safetensors` + `actor.json` (the
            actor of the last checkpoint), `progress.jsonl` (one line per `log_every` steps).
        info: provenance written into every exported actor's JSON (command, ...).
        callbacks: extra stable-baselines3 callbacks (tests use one to simulate a kill).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with _exclusive(out):
        return _train(cfg, out, info, callbacks)


@contextlib.contextmanager
def _exclusive(out: Path) -> Iterator[None]:
    """One trainer per folder (the OS drops the lock when its holder dies, even by SIGKILL)."""
    with (out / ".lock").open("w") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise UserError(
                f"another process is training in {out}; wait for it or stop it"
            ) from None
        _recover(out)
        yield


def _recover(out: Path) -> None:
    """Tidy what a kill during a checkpoint write left (see `pipeline.io.atomic_dir`).

    Killed between moving the old checkpoint aside and moving the new one in, there is no
    `resume/` but a complete `.old-resume.*`: put it back. Half-written `.tmp-resume.*` folders
    (about 200 MB each) are removed.
    """
    folder = resume_dir(out)
    aside = sorted(out.glob(f".old-{folder.name}.*"), key=lambda p: p.stat().st_mtime)
    if not folder.exists() and aside and (aside[-1] / _STATE).exists():
        aside[-1].rename(folder)
        log.info("recovered the checkpoint moved aside by a killed run")
    for stale in [*out.glob(f".old-{folder.name}.*"), *out.glob(f".tmp-{folder.name}.*")]:
        shutil.rmtree(stale, ignore_errors=True)


def _train(
    cfg: SACParams, out: Path, info: dict[str, Any] | None, callbacks: Sequence[BaseCallback]
) -> TrainSummary:
    torch.set_num_threads(cfg.threads)
    env = flips = UpsideDownEnd(make_direction_env(cfg.resample_interval, cfg.max_episode_steps))
    try:
        folder = resume_dir(out)
        if (folder / _STATE).exists():
            model = _load(cfg, env, folder)
            log.info("resuming from step %d (%s)", model.num_timesteps, folder)
        else:
            model = build_sac(cfg, env)
        start = model.num_timesteps
        actor_info = {
            "robot": "ant",
            "env": "online-ant-v0 + GymXYWrapper (OGBench)",
            "observation": "ant qpos[2:] (13) + qvel (14) + commanded unit direction (2)",
            "action": "deterministic: tanh(mean) rescaled to the action bounds",
            "trainer": "stable-baselines3 SAC",
            "seed": cfg.seed,
            "sac": cfg.model_dump(),
            **(info or {}),
        }
        t0 = time.monotonic()
        remaining = cfg.total_steps - start
        if remaining > 0:
            noise = _PhaseNoise(int(env.action_space.shape[0]))
            model.action_noise = noise
            checkpointer = _Checkpointer(cfg, out, actor_info, start, flips, noise)
            try:
                with _checkpoint_on_signals(checkpointer):
                    model.learn(
                        total_timesteps=remaining,
                        callback=[checkpointer, *callbacks],
                        reset_num_timesteps=start == 0,
                        log_interval=None,  # no stable-baselines3 logs: the progress bar reports
                    )
            except _Stopped as stop:
                log.info("signal %s: checkpointed step %d and stopped", stop, model.num_timesteps)
        seconds = time.monotonic() - t0
        steps = model.num_timesteps
    finally:
        env.close()
    return TrainSummary(
        steps=steps,
        start_steps=start,
        finished=steps >= cfg.total_steps,
        seconds=seconds,
        steps_per_s=(steps - start) / seconds if seconds > 0 else 0.0,
    )
