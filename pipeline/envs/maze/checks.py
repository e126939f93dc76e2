"""Sanity checks on a maze dataset, in the spirit of Minari's `check_maze_dataset.py`.

Checks shapes, finite values, action range, the clock, that positions never jump (no hidden
resets), that the ball stays inside the maze and out of the walls, that the recorded physics
agrees with the observations, and how often the demonstrator reaches its goals. Episodes are
consumed one at a time, so a dataset streamed from disk is never held in memory.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.dataset import DatasetInfo, Episode
from pipeline.envs.disturbance import AGENT_BODY, Pushes
from pipeline.envs.maze.env import (
    AGENT_RADIUS,
    MAX_AXIS_SPEED,
    SUPPORTED_ENVS,
    make_maze_env,
    maze_layout,
)
from pipeline.errors import UserError

# Largest velocity change one step can add (m/s): max force 100 N on the 4.19 kg ball for 0.01 s
# is 0.24 m/s; wall contacts add a little. Recorded speeds above the clip plus this are suspect.
_SPEED_SLACK = 1.0
# Recorded physics must equal the observations (the built-in expert copies them bit for bit;
# this leaves room for float32 imports).
_PHYSICS_ATOL = 1e-5


@dataclass
class DatasetReport:
    """What `check_maze_dataset` (or `check_ogbench_dataset`) measured, and the problems found."""

    n_episodes: int = 0
    """Episodes seen."""
    n_steps: int = 0
    """Steps seen, over all episodes."""
    goals_reached: int | None = None
    """Steps flagged `goal_reached` (None if the dataset has no goal data)."""
    goals_per_1000_steps: float | None = None
    """Goal-reach rate of the demonstrator."""
    mean_steps_per_goal: float | None = None
    """Steps divided by goals reached (inf if none)."""
    longest_goal_segment: int | None = None
    """Most steps spent pursuing one goal, the unfinished last one included."""
    max_step_distance: float = 0.0
    """Largest |position change| between consecutive steps (m)."""
    max_axis_speed: float = 0.0
    """Largest |vx| or |vy| (m/s)."""
    min_wall_clearance: float = math.inf
    """Smallest gap between the ball's surface and a wall (m); negative means penetration."""
    n_outside_bounds: int = 0
    """States whose position lies outside the maze's outer boundary."""
    n_in_wall: int = 0
    """States whose ball centre lies inside a wall cell."""
    n_nonfinite: int = 0
    """Steps with a NaN or infinite value in any array."""
    episodes_reaching_goal: int | None = None
    """OGBench data: episodes in which a goal was reached at least once."""
    fallen_steps: int | None = None
    """Ant data: steps with the torso outside the healthy height range or upside down."""
    fallen_episodes: int | None = None
    """Ant data: episodes with at least one fallen step."""
    min_torso_height: float | None = None
    """Ant data: lowest torso height (m)."""
    max_velocity_mismatch: float | None = None
    """Ant data: largest gap between a step's torso move and what its velocities explain (m)."""
    problems: list[str] = field(default_factory=list)
    """One line per kind of problem found (first occurrence and count)."""

    @property
    def ok(self) -> bool:
        """True if no problem was found."""
        return not self.problems

    def metrics(self) -> dict[str, float]:
        """The numbers as a flat dict of floats (Nones left out), e.g. for dvclive."""
        out: dict[str, float] = {}
        for name, value in vars(self).items():
            if isinstance(value, int | float) and not isinstance(value, bool):
                out[name] = float(value)
        out["n_problems"] = float(len(self.problems))
        return out


class _Problems:
    """Collects problems by kind, keeping the first message of each and a count."""

    def __init__(self) -> None:
        self._kinds: dict[str, list[Any]] = {}

    def add(self, kind: str, message: str, count: int = 1) -> None:
        if kind in self._kinds:
            self._kinds[kind][1] += count
        else:
            self._kinds[kind] = [message, count]

    def lines(self) -> list[str]:
        return [msg if n == 1 else f"{msg} ({n} occurrences)" for msg, n in self._kinds.values()]


def _push_speed(info: DatasetInfo) -> float:
    """Largest velocity change (m/s) one recorded push can add (`Pushes`: impulse / the agent's
    mass); 0 for a dataset recorded without pushes."""
    pushes = Pushes.of_dataset(info.generator)
    if not pushes.active:
        return 0.0
    env = make_maze_env(info.env_id, info.env_kwargs.get("maze_map"))
    try:
        return pushes.impulse / float(env.unwrapped.model.body_mass[AGENT_BODY])
    finally:
        env.close()


def _layout_for(info: DatasetInfo) -> dict[str, Any]:
    """The maze layout recorded in `info`, or rebuilt from its env id and kwargs."""
    recorded = info.generator.get("maze_layout")
    if recorded is not None:
        return recorded
    maze_map = info.env_kwargs.get("maze_map")
    env = make_maze_env(info.env_id, maze_map)
    try:
        return maze_layout(env)
    finally:
        env.close()


class _Walls:
    """Vectorized wall geometry of a layout: bounds, wall cells and ball clearance."""

    def __init__(self, layout: dict[str, Any]):
        self.scale = float(layout["maze_size_scaling"])
        self.xc, self.yc = float(layout["x_map_center"]), float(layout["y_map_center"])
        self.radius = float(layout.get("agent_radius", AGENT_RADIUS))
        self.bounds = layout["bounds"]
        walls = np.array([[c == 1 for c in row] for row in layout["maze_map"]])
        # One ring of padding counted as wall, so points just outside the map index safely.
        self.wall = np.pad(walls, 1, constant_values=True)

    def measure(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For positions `[N, 2]`: outside-bounds mask, in-wall mask, clearance (m) `[N]`."""
        xmin, xmax, ymin, ymax = self.bounds
        x, y = pos[:, 0], pos[:, 1]
        outside = (x < xmin) | (x > xmax) | (y < ymin) | (y > ymax)
        col_f = (x + self.xc) / self.scale
        row_f = (self.yc - y) / self.scale
        n_rows, n_cols = self.wall.shape
        i = np.clip(np.floor(row_f).astype(np.int64) + 1, 1, n_rows - 2)
        j = np.clip(np.floor(col_f).astype(np.int64) + 1, 1, n_cols - 2)
        in_wall = self.wall[i, j] & ~outside
        gap = np.full(len(pos), np.inf)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                is_wall = self.wall[i + di, j + dj]
                # Distance (cell units) from the point to the box of cell (i + di, j + dj).
                top, left = i + di - 1, j + dj - 1
                dx = np.maximum(np.maximum(left - col_f, col_f - (left + 1)), 0.0)
                dy = np.maximum(np.maximum(top - row_f, row_f - (top + 1)), 0.0)
                dist = np.where(is_wall, np.hypot(dx, dy) * self.scale, np.inf)
                gap = np.minimum(gap, dist)
        clearance = np.where(in_wall, -self.radius, gap - self.radius)
        return outside, in_wall, clearance


def _check_shapes(ep: Episode, info: DatasetInfo, problems: _Problems) -> bool:
    """Record shape problems of one episode; True if its arrays are usable."""
    n = len(ep)
    expected: dict[str, tuple[int, ...] | None] = {
        "observations": (n, info.state_dim),
        "actions": (n, info.action_dim),
        "time": (n,),
        "physics": (n, info.physics_dim) if info.physics_dim else None,
        "goals": (n, info.goal_dim) if info.goal_dim else None,
        "goal_reached": (n,),
        "rewards": (n,),
        "terminals": (n,),
    }
    usable = n > 0
    if n == 0:
        problems.add("empty", f"episode {ep.index} has no steps")
    for name, shape in expected.items():
        array = getattr(ep, name)
        if array is None:
            if name in ("physics", "goals") and shape is not None:
                problems.add(f"missing {name}", f"episode {ep.index}: {name} is missing")
                usable = False
            continue
        if shape is None:
            problems.add(f"extra {name}", f"episode {ep.index} has {name}; info says it has none")
        elif array.shape != shape:
            problems.add(
                f"shape {name}",
                f"episode {ep.index}: {name} has shape {array.shape}, expected {shape}",
            )
            usable = False
    return usable


def check_maze_dataset(
    episodes: Iterable[Episode],
    info: DatasetInfo,
    layout: dict[str, Any] | None = None,
    continuous: bool | None = None,
    max_step_distance: float | None = None,
    max_penetration: float = 0.075,
    min_goals_per_1000_steps: float = 1.0,
    max_goal_segment: int | None = None,
) -> DatasetReport:
    """Check a maze dataset whose states start with `[x, y, vx, vy]`.

    Args:
        episodes: The episodes, in order (any iterable; consumed once).
        info: The dataset's metadata (state layout, control period, env).
        layout: `maze_layout` of the maze; taken from `info.generator["maze_layout"]` or rebuilt
            from `info.env_id` / `info.env_kwargs` if None.
        continuous: Whether episode k + 1 continues episode k physically (positions checked for
            jumps across the boundary too); default: True for the built-in expert (source
            "maze").
        max_step_distance: Largest allowed |position change| per step (m); default
            2 * sqrt(2) * 5 m/s * control_period: the velocity clip allows at most
            sqrt(2) * 5.24 m/s, doubled for contact bounces; a reset jumps much further. A
            dataset recorded with random pushes (`generator["disturbance"]`) gets the velocity
            change of one push added to the speed in this and in the speed check.
        max_penetration: Largest allowed overlap of the ball (radius 0.1 m) with a wall (m);
            MuJoCo's soft contacts let a 5 m/s ball in by up to ~0.05 m (measured over 1M steps).
        min_goals_per_1000_steps: Lowest acceptable goal-reach rate (the D4RL-like expert reaches
            about 4.5 (Large) to 12 (UMaze) goals per 1000 steps).
        max_goal_segment: Most steps allowed on one goal; default twice the env's D4RL episode
            limit (600 for Medium), None for an unknown env.

    Returns:
        The report; `report.problems` is empty if all checks passed.
    """
    problems = _Problems()
    report = DatasetReport()
    if info.state_names[:4] != ["x", "y", "vx", "vy"]:
        raise UserError(
            f"dataset {info.name!r} is not a point-maze dataset: its states are "
            f"{info.state_names}, expected x, y, vx, vy first"
        )
    dt = float(info.control_period)
    walls = _Walls(layout if layout is not None else _layout_for(info))
    if continuous is None:
        continuous = info.source == "maze"
    push_speed = _push_speed(info)
    if max_step_distance is None:
        max_step_distance = 2.0 * math.sqrt(2.0) * (MAX_AXIS_SPEED + push_speed) * dt
    if max_goal_segment is None and info.env_id in SUPPORTED_ENVS:
        max_goal_segment = 2 * SUPPORTED_ENVS[info.env_id]
    prev: Episode | None = None
    segment = 0
    has_goals = True
    for k, ep in enumerate(episodes):
        report.n_episodes += 1
        report.n_steps += len(ep)
        if ep.index != k:
            problems.add("index", f"episode at position {k} has index {ep.index}")
        if not _check_shapes(ep, info, problems):
            prev = None
            continue
        _check_values(
            ep, info, walls, max_step_distance, push_speed, max_penetration, report, problems
        )
        if prev is not None:
            _check_boundary(prev, ep, dt, continuous, max_step_distance, report, problems)
        if ep.goal_reached is None or ep.goals is None:
            has_goals = False
        else:
            segment = _check_goals(ep, segment, report, problems)
            if not continuous:
                segment = 0
        prev = ep
    if report.n_episodes == 0:
        problems.add("no episodes", "the dataset has no episodes")
    if has_goals:
        _judge_goals(report, min_goals_per_1000_steps, max_goal_segment, problems)
    else:
        report.goals_reached = report.longest_goal_segment = None
    report.problems = problems.lines()
    return report


def _check_values(
    ep: Episode,
    info: DatasetInfo,
    walls: _Walls,
    max_step: float,
    push_speed: float,
    max_penetration: float,
    report: DatasetReport,
    problems: _Problems,
) -> None:
    """Finite values, action range, clock, physics, jumps, bounds and walls of one episode."""
    arrays = [ep.observations, ep.actions, ep.time[:, None]]
    arrays += [a for a in (ep.physics, ep.goals) if a is not None]
    finite = np.all(np.concatenate([np.isfinite(a).all(axis=1)[:, None] for a in arrays], 1), 1)
    if not finite.all():
        bad = int(np.sum(~finite))
        report.n_nonfinite += bad
        t = int(np.argmin(finite))
        problems.add("nonfinite", f"episode {ep.index} step {t}: NaN or inf values", bad)
        return
    if np.abs(ep.actions).max() > 1.0 + 1e-9:
        t = int(np.argmax(np.abs(ep.actions).max(axis=1)))
        problems.add(
            "actions", f"episode {ep.index} step {t}: action {ep.actions[t]} outside [-1, 1]"
        )
    steps = np.diff(ep.time)
    if steps.size and np.abs(steps - info.control_period).max() > 1e-6:
        t = int(np.argmax(np.abs(steps - info.control_period)))
        problems.add("time", f"episode {ep.index} step {t}: time advances by {steps[t]:.6g} s")
    if ep.physics is not None and info.physics_dim == 1 + info.state_dim == 5:
        if np.abs(ep.physics[:, 1:] - ep.observations).max() > _PHYSICS_ATOL:
            problems.add("physics", f"episode {ep.index}: physics qpos/qvel differ from states")
        # MuJoCo accumulates `time += 0.01`, which drifts ~1e-10 relative from `step * dt`.
        drift = np.abs(ep.physics[:, 0] - ep.time) - 1e-9 * np.abs(ep.time)
        if drift.max() > _PHYSICS_ATOL:
            problems.add("physics time", f"episode {ep.index}: physics time differs from time")
    pos = ep.observations[:, :2]
    jumps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    if jumps.size:
        report.max_step_distance = max(report.max_step_distance, float(jumps.max()))
        if jumps.max() > max_step:
            t = int(np.argmax(jumps))
            problems.add(
                "jump",
                f"episode {ep.index} step {t}: position jumps {jumps[t]:.3f} m in one step "
                f"(max {max_step:.3f})",
                int(np.sum(jumps > max_step)),
            )
    speed = float(np.abs(ep.observations[:, 2:4]).max())
    report.max_axis_speed = max(report.max_axis_speed, speed)
    if speed > MAX_AXIS_SPEED + _SPEED_SLACK + push_speed:
        problems.add("speed", f"episode {ep.index}: speed {speed:.2f} m/s on one axis")
    outside, in_wall, clearance = walls.measure(pos)
    report.n_outside_bounds += int(outside.sum())
    report.n_in_wall += int(in_wall.sum())
    report.min_wall_clearance = min(report.min_wall_clearance, float(clearance.min()))
    if outside.any():
        t = int(np.argmax(outside))
        problems.add(
            "bounds",
            f"episode {ep.index} step {t}: {pos[t]} is outside the maze",
            int(outside.sum()),
        )
    if in_wall.any():
        t = int(np.argmax(in_wall))
        problems.add(
            "wall", f"episode {ep.index} step {t}: {pos[t]} is inside a wall", int(in_wall.sum())
        )
    elif clearance.min() < -max_penetration:
        t = int(np.argmin(clearance))
        problems.add(
            "penetration",
            f"episode {ep.index} step {t}: the ball overlaps a wall by {-clearance[t]:.3f} m",
            int(np.sum(clearance < -max_penetration)),
        )


def _check_boundary(
    prev: Episode,
    ep: Episode,
    dt: float,
    continuous: bool,
    max_step: float,
    report: DatasetReport,
    problems: _Problems,
) -> None:
    """Episode `ep` continues `prev` on the clock (and in space if `continuous`)."""
    gap = float(ep.time[0] - prev.time[-1])
    if abs(gap - dt) > 1e-6:
        problems.add(
            "clock",
            f"episode {ep.index} starts {gap:.6g} s after episode {prev.index} ends "
            f"(expected {dt:.6g} s)",
        )
    if continuous:
        jump = float(np.linalg.norm(ep.observations[0, :2] - prev.observations[-1, :2]))
        report.max_step_distance = max(report.max_step_distance, jump)
        if jump > max_step:
            problems.add(
                "boundary jump",
                f"episode {ep.index} starts {jump:.3f} m away from where episode {prev.index} "
                "ended",
            )


def _check_goals(ep: Episode, segment: int, report: DatasetReport, problems: _Problems) -> int:
    """Count reached goals, check goals change only after being reached; returns open segment."""
    reached = ep.goal_reached.astype(bool)
    report.goals_reached = (report.goals_reached or 0) + int(reached.sum())
    changed = np.any(ep.goals[1:] != ep.goals[:-1], axis=1)
    unexplained = changed & ~reached[:-1]
    if unexplained.any():
        t = int(np.argmax(unexplained))
        problems.add(
            "goal switch",
            f"episode {ep.index} step {t + 1}: the goal changes without having been reached",
            int(unexplained.sum()),
        )
    # Runs of steps spent on each goal (first step on it to the step that reached it), with the
    # run left open by the previous episodes added to the first one.
    longest = report.longest_goal_segment or 0
    ends = np.flatnonzero(reached)
    if ends.size:
        lengths = np.diff(np.concatenate([[-1], ends]))
        lengths[0] += segment
        longest = max(longest, int(lengths.max()))
        segment = len(reached) - 1 - int(ends[-1])
    else:
        segment += len(reached)
    report.longest_goal_segment = max(longest, segment)
    return segment


def _judge_goals(
    report: DatasetReport, min_rate: float, max_segment: int | None, problems: _Problems
) -> None:
    """Derive the goal-reach rates once all episodes are seen, and flag a slow demonstrator."""
    if report.n_steps == 0 or report.goals_reached is None:
        return
    rate = 1000.0 * report.goals_reached / report.n_steps
    report.goals_per_1000_steps = rate
    report.mean_steps_per_goal = (
        report.n_steps / report.goals_reached if report.goals_reached else math.inf
    )
    # Below 1000 steps a slow goal is not yet evidence of anything.
    if report.n_steps >= 1000 and rate < min_rate:
        problems.add(
            "goal rate",
            f"the demonstrator reaches only {rate:.2f} goals per 1000 steps (expected >= "
            f"{min_rate})",
        )
    if max_segment is not None and (report.longest_goal_segment or 0) > max_segment:
        problems.add(
            "goal segment",
            f"the demonstrator spent {report.longest_goal_segment} steps on one goal "
            f"(expected <= {max_segment}): stuck?",
        )


def raise_for_problems(report: DatasetReport, name: str = "dataset") -> None:
    """Raise `UserError` (one line) listing the report's problems, if any."""
    if report.problems:
        shown = "; ".join(report.problems[:5])
        more = f"; and {len(report.problems) - 5} more" if len(report.problems) > 5 else ""
        raise UserError(f"{name} failed {len(report.problems)} check(s): {shown}{more}")
