"""Quality of a direction-commanded ant actor: speed along the command, and maze navigation.

1. Direction task (`online-ant-v0` in OGBench's `GymXYWrapper`): mean speed along the commanded
   direction (m/s; displacement along it per step / dt), the sideways speed, falls (episodes
   ended by the unhealthy check) and flips (episodes in which the ant was ever upside down);
   once noise-free and once with OGBench's data noise on the actions (`check.action_noise`).
2. Maze navigation as OGBench makes its data (`data_gen_scripts/generate_locomaze.py`), noise-free:
   each step the BFS oracle's next cell gives the direction, the actor walks it. Success on the
   maze's five evaluation tasks (`reset(options={"task_id": i})`, i = 1..5; within 0.5 of the goal
   within 1000 steps, the episode ends on success), with 95 % Wilson intervals.

The actor acts deterministically (tanh of the mean); OGBench's data adds Gaussian noise on top.
"""

from __future__ import annotations

import numpy as np

from pipeline.ant_expert.actor import DirectionActor
from pipeline.ant_expert.config import ExpertCheckParams
from pipeline.envs.ant import (
    expert_observation,
    global_seed,
    make_ant_maze,
    make_direction_env,
    oracle_direction,
    torso_up,
)
from pipeline.evaluation.proportions import wilson_interval


def direction_speed(
    actor: DirectionActor,
    episodes: int,
    seed: int,
    resample_interval: int = 100,
    max_episode_steps: int = 1000,
    action_noise: float = 0.0,
) -> dict:
    """Mean speed along (and across) the commanded direction over `episodes` episodes, with
    Gaussian noise of std `action_noise` on the actor's actions (clipped to their bounds)."""
    along: list[float] = []
    across: list[float] = []
    lengths: list[int] = []
    falls = flips = 0
    noise = np.random.default_rng(seed)
    low = np.asarray(actor.spec.action_low)
    high = np.asarray(actor.spec.action_high)
    with global_seed(seed):
        env = make_direction_env(resample_interval, max_episode_steps)
        try:
            dt = float(env.unwrapped.dt)
            obs, _ = env.reset(seed=seed)
            for _ in range(episodes):
                obs, _ = env.reset()
                done, steps, forward, sideways, flipped = False, 0, 0.0, 0.0, False
                while not done:
                    xy = env.unwrapped.data.qpos[:2].copy()
                    direction = obs[-2:].copy()
                    action = actor.act(obs)
                    if action_noise > 0:
                        action = np.clip(
                            action + noise.normal(0.0, action_noise, action.shape), low, high
                        )
                    obs, reward, terminated, truncated, info = env.step(action)
                    flipped = flipped or bool(torso_up(env.unwrapped.data.qpos[3:7]) < 0.0)
                    delta = info["xy"] - xy
                    forward += float(reward)
                    sideways += abs(float(delta[0] * -direction[1] + delta[1] * direction[0]))
                    steps += 1
                    done = terminated or truncated
                falls += int(terminated)
                flips += int(flipped)
                lengths.append(steps)
                along.append(forward / (steps * dt))
                across.append(sideways / (steps * dt))
        finally:
            env.close()
    return {
        "episodes": episodes,
        "speed_along_command_mean": float(np.mean(along)),
        "speed_along_command_min": float(np.min(along)),
        "speed_across_command_mean": float(np.mean(across)),
        "action_noise": action_noise,
        "falls": falls,
        "flips": flips,
        "episode_steps_mean": float(np.mean(lengths)),
        "dt": dt,
    }


def _rate(successes: int, n: int) -> dict:
    lo, hi = wilson_interval(successes, n)
    return {
        "episodes": n,
        "successes": successes,
        "success_rate": successes / n if n else 0.0,
        "success_ci95_low": round(lo, 4),
        "success_ci95_high": round(hi, 4),
    }


def maze_success(
    actor: DirectionActor, env_id: str, episodes_per_task: int, max_episode_steps: int, seed: int
) -> dict:
    """Success of the oracle-driven actor on the maze's evaluation tasks, per task and overall."""
    tasks = []
    with global_seed(seed):
        env = make_ant_maze(env_id, max_episode_steps)
        try:
            env.reset(seed=seed)
            env.unwrapped.action_space.seed(seed)  # the random settling steps of OGBench's reset
            for task_id in range(1, env.unwrapped.num_tasks + 1):
                wins, steps_to_goal = 0, []
                for _ in range(episodes_per_task):
                    ob, _ = env.reset(options={"task_id": task_id})
                    done, steps, success = False, 0, False
                    while not done:
                        obs = expert_observation(ob, oracle_direction(env))
                        ob, _, terminated, truncated, info = env.step(actor.act(obs))
                        steps += 1
                        success = success or bool(info["success"])
                        done = terminated or truncated
                    wins += int(success)
                    if success:
                        steps_to_goal.append(steps)
                tasks.append(
                    {
                        "task_id": task_id,
                        **_rate(wins, episodes_per_task),
                        "steps_to_goal_mean": float(np.mean(steps_to_goal))
                        if steps_to_goal
                        else None,
                    }
                )
        finally:
            env.close()
    total = sum(t["successes"] for t in tasks)
    return {"tasks": tasks, "overall": _rate(total, episodes_per_task * len(tasks))}


def check_direction_actor(actor: DirectionActor, cfg: ExpertCheckParams) -> dict:
    """The speed check and every maze in `cfg.mazes`, as one JSON-ready dict."""
    sac = actor.spec.info.get("sac", {})

    def speed_check(episodes: int, seed: int, action_noise: float = 0.0) -> dict:
        return direction_speed(
            actor,
            episodes,
            seed,
            resample_interval=sac.get("resample_interval", 100),
            max_episode_steps=sac.get("max_episode_steps", 1000),
            action_noise=action_noise,
        )

    speed = speed_check(cfg.speed_episodes, cfg.seed)
    noisy = (
        speed_check(cfg.noisy_episodes, cfg.seed + 1, cfg.action_noise)
        if cfg.noisy_episodes
        else None
    )
    mazes = {
        env_id: maze_success(actor, env_id, cfg.episodes_per_task, cfg.max_episode_steps, cfg.seed)
        for env_id in cfg.mazes
    }
    return {"check": cfg.model_dump(), "speed": speed, "noisy": noisy, "mazes": mazes}


def summary_lines(quality: dict) -> list[str]:
    """A few human-readable lines of a `check_direction_actor` result."""
    s = quality["speed"]
    lines = [
        f"direction task: {s['speed_along_command_mean']:.3f} m/s along the command "
        f"(min {s['speed_along_command_min']:.3f}), {s['speed_across_command_mean']:.3f} m/s "
        f"across, {s['falls']} falls in {s['episodes']} episodes"
    ]
    if n := quality.get("noisy"):
        lines.append(
            f"with action noise {n['action_noise']}: {n['speed_along_command_mean']:.3f} m/s, "
            f"{n['flips']} of {n['episodes']} episodes upside down, {n['falls']} falls"
        )
    for env_id, maze in quality["mazes"].items():
        o = maze["overall"]
        per_task = " ".join(f"{t['successes']}/{t['episodes']}" for t in maze["tasks"])
        lines.append(
            f"{env_id}: success {o['success_rate']:.1%} [{o['success_ci95_low']:.1%}, "
            f"{o['success_ci95_high']:.1%}] ({o['successes']}/{o['episodes']}; tasks {per_task})"
        )
    return lines
