"""Checks of an OGBench maze dataset (generated or imported), one episode at a time.

Both locomotors: finite values, actions in [-1, 1], positions in the maze's free cells (and the
body's smallest clearance to a wall, negative inside one), recorded physics equal to the
observations, the goal-reach rate when goals are recorded. Steps that start at an inbound teleport
(the teleport mazes) are exempt from the jump checks. The point: no jump beyond a step's
reach. The ant (issue 19): falls (torso height outside OGBench's healthy [0.2, 1.0] m, the range
its direction task ends episodes on, or the torso upside down), and jumps (a torso move beyond a
step's reach, or one its recorded velocities do not explain: a hidden reset or a teleport).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from pipeline.dataset import DatasetInfo, Episode
from pipeline.envs.maze.checks import DatasetReport
from pipeline.envs.maze.checks import _Walls as MazeWalls  # the maze checks' wall geometry
from pipeline.envs.ogbench import ANT_HEALTHY_Z, OGBenchMazeSpec, ant_fallen
from pipeline.sources.ogbench.info import ogbench_spec

# The point's command moves it at most 0.2 m per axis a step, and a wall contact can push it a
# little further (measured: up to 0.29 m in 200k generated steps); a hidden reset jumps cells.
_MAX_POINT_STEP = 1.0
# Recorded physics must equal the observations (float32 files leave ~1e-6 of room).
_PHYSICS_ATOL = 1e-4
# The ant's torso moves at most ~0.3 m in a 0.1 s step (measured: 0.31 m at most in generated
# navigate data, at ~1.5 m/s walking); 1 m in one step is 10 m/s, beyond any gait.
_MAX_ANT_STEP = 1.0
# |torso displacement - dt * mean of the velocities before and after| over one step (m): the
# trapezoid rule's error, at most ~0.1 m in generated data (contacts jolt the velocity inside a
# step); a state that did not follow from the one before misses it by far more.
_MAX_ANT_MISMATCH = 0.5
# Share of an ant dataset's steps allowed fallen before ingest fails. OGBench keeps episodes in
# which the ant flips (a flipped ant stays flipped). Our expert under OGBench's noise 0.2 ends
# 14 of 100 antmaze-medium-navigate episodes flipped (8.6 % of the steps), 2 of 50 large ones
# (1.8 %); a share beyond this means a weaker expert or more noise than that.
MAX_FALLEN_SHARE = 0.15


def check_ogbench_dataset(
    episodes: Iterable[Episode],
    info: DatasetInfo,
    max_fallen_share: float = MAX_FALLEN_SHARE,
) -> DatasetReport:
    """Check an OGBench point- or ant-maze dataset (see the module docstring).

    Args:
        episodes: The episodes, in order (any iterable; consumed once).
        info: The dataset's metadata (`env_id` an OGBench maze).
        max_fallen_share: The ant: largest share of steps with the ant fallen before that is a
            problem.

    Returns:
        The report; `report.problems` is empty if all checks passed (at most 20 listed).
    """
    spec = ogbench_spec(info.env_id)
    walls = MazeWalls(spec.layout)
    report, problems = DatasetReport(), []
    reached, reaching, has_goals = 0, 0, True
    if spec.loco == "ant":
        report.fallen_steps = report.fallen_episodes = 0
        report.max_velocity_mismatch = 0.0
        report.min_torso_height = np.inf
    for ep in episodes:
        report.n_episodes += 1
        report.n_steps += len(ep)
        arrays = [ep.observations, ep.actions] + [a for a in (ep.physics,) if a is not None]
        finite = np.all([np.isfinite(a).all(axis=1) for a in arrays], axis=0)
        if not finite.all():
            report.n_nonfinite += int((~finite).sum())
            problems.append(f"episode {ep.index}: NaN or inf values")
            continue
        if np.abs(ep.actions).max() > 1.0 + 1e-6:
            problems.append(f"episode {ep.index}: actions outside [-1, 1]")
        _check_walls(ep, walls, report, problems)
        _check_physics(ep, spec, problems)
        # Steps from an inbound teleport move the agent to an outbound one: no jump to check.
        moves = np.ones(max(len(ep) - 1, 0), dtype=bool)
        if spec.teleports is not None:
            moves = ~spec.teleports.inside(ep.observations[:-1, :2])
        if spec.loco == "point":
            _check_point_steps(ep, moves, report, problems)
        else:
            _check_ant(ep, spec, moves, report, problems)
        if ep.goal_reached is None:
            has_goals = False
        else:
            reached += int(ep.goal_reached.sum())
            reaching += int(ep.goal_reached.any())
    if report.n_episodes == 0:
        problems.append("the dataset has no episodes")
    if has_goals and report.n_steps:
        report.goals_reached = reached
        report.goals_per_1000_steps = 1000.0 * reached / report.n_steps
        report.episodes_reaching_goal = reaching
    if spec.loco == "ant" and report.n_steps:
        share = report.fallen_steps / report.n_steps
        if share > max_fallen_share:
            problems.append(
                f"the ant is fallen (torso below {ANT_HEALTHY_Z[0]} m, above "
                f"{ANT_HEALTHY_Z[1]} m or upside down) in {share:.1%} of the steps "
                f"({report.fallen_episodes} episodes), more than {max_fallen_share:.1%}"
            )
    report.problems = problems[:20]
    return report


def _check_walls(ep: Episode, walls: MazeWalls, report: DatasetReport, problems: list[str]) -> None:
    outside, in_wall, clearance = walls.measure(ep.observations[:, :2])
    report.n_outside_bounds += int(outside.sum())
    report.n_in_wall += int(in_wall.sum())
    report.min_wall_clearance = min(report.min_wall_clearance, float(clearance.min()))
    if outside.any() or in_wall.any():
        problems.append(f"episode {ep.index}: positions in walls or outside the maze")


def _check_physics(ep: Episode, spec: OGBenchMazeSpec, problems: list[str]) -> None:
    """The physics state `[time, qpos, qvel]` must hold the observation: the point's `[x, y]`
    = qpos, the ant's `qpos + qvel`."""
    if ep.physics is None:
        return
    nq, nv = spec.model.nq, spec.model.nv
    if ep.physics.shape[1] != 1 + nq + nv:
        problems.append(f"episode {ep.index}: physics states of the wrong size")
        return
    observed = ep.physics[:, 1 : 1 + spec.state_dim]
    if np.abs(observed - ep.observations).max() > _PHYSICS_ATOL:
        problems.append(f"episode {ep.index}: physics qpos differ from the observations")


def _check_point_steps(
    ep: Episode, moves: np.ndarray, report: DatasetReport, problems: list[str]
) -> None:
    """Steps `moves [N - 1]` (those not from a teleport) stay within a step's reach."""
    if not moves.any():
        return
    jump = float(np.linalg.norm(np.diff(ep.observations[:, :2], axis=0), axis=1)[moves].max())
    report.max_step_distance = max(report.max_step_distance, jump)
    if jump > _MAX_POINT_STEP:
        problems.append(f"episode {ep.index}: the point jumps {jump:.3f} m in one step")


def ant_jumps(observations: np.ndarray, nq: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """`[N - 1]` torso displacement per step (m) and its mismatch with the recorded velocities
    (m): |p_{t+1} - p_t - dt (v_t + v_{t+1}) / 2|, p = `qpos[:3]`, v = `qvel[:3]` (world frame)."""
    position, velocity = observations[:, :3], observations[:, nq : nq + 3]
    moved = np.diff(position, axis=0)
    mismatch = moved - 0.5 * dt * (velocity[:-1] + velocity[1:])
    return np.linalg.norm(moved, axis=1), np.linalg.norm(mismatch, axis=1)


def _check_ant(
    ep: Episode,
    spec: OGBenchMazeSpec,
    moves: np.ndarray,
    report: DatasetReport,
    problems: list[str],
) -> None:
    obs = ep.observations
    fallen = ant_fallen(obs)
    report.fallen_steps += int(fallen.sum())
    report.fallen_episodes += int(fallen.any())
    report.min_torso_height = min(report.min_torso_height, float(obs[:, 2].min()))
    nq = spec.model.nq
    report.max_axis_speed = max(report.max_axis_speed, float(np.abs(obs[:, nq : nq + 2]).max()))
    if not moves.any():
        return
    moved, mismatch = ant_jumps(obs, nq, spec.dt)
    moved, mismatch = np.where(moves, moved, 0.0), np.where(moves, mismatch, 0.0)
    report.max_step_distance = max(report.max_step_distance, float(moved.max()))
    report.max_velocity_mismatch = max(report.max_velocity_mismatch, float(mismatch.max()))
    if moved.max() > _MAX_ANT_STEP or mismatch.max() > _MAX_ANT_MISMATCH:
        t = int(np.argmax(np.maximum(moved / _MAX_ANT_STEP, mismatch / _MAX_ANT_MISMATCH)))
        problems.append(
            f"episode {ep.index}: the ant's torso jumps {moved[t]:.3f} m at step {t} (its "
            f"velocities explain all but {mismatch[t]:.3f} m): a hidden reset or teleport?"
        )
