"""Scripted maze expert in the manner of D4RL's maze2d `WaypointController`.

It plans a path of grid cells to its goal cell by breadth-first search over the free cells, follows
the cell centres with a PD controller `a = p_gain * (waypoint - pos) + d_gain * vel`, adds Gaussian
noise and clips to [-1, 1]. When the ball comes within `goal_radius` of the goal it draws a new
random goal and replans, without resetting the simulation (one continuous stream, as in D4RL's
`generate_maze2d_datasets.py`). Defaults are D4RL's: p_gain 10, d_gain -1, switch waypoints within
0.1 m, noise sigma 0.5, goal radius 0.5 m.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from pydantic import ConfigDict, with_config

from pipeline.envs.ids import Cell, layout_cell
from pipeline.errors import UserError

# 4-connected moves (row, col), in the fixed order that breaks ties between equally short paths.
_MOVES: tuple[Cell, ...] = ((-1, 0), (1, 0), (0, -1), (0, 1))
# Noise samples drawn per refill: amortizes the Generator call over many steps.
_NOISE_BLOCK = 4096
# Redraws of a goal position that falls within goal_radius of the ball before giving up.
_GOAL_TRIES = 100


@with_config(ConfigDict(extra="forbid"))  # as `ingest.expert` in params.yaml: no unknown keys
@dataclass
class ExpertConfig:
    """Parameters of the scripted expert (defaults: D4RL maze2d, noisy variant)."""

    p_gain: float = 10.0
    """Proportional gain on `waypoint - position` (1/m)."""
    d_gain: float = -1.0
    """Derivative gain on the velocity (s/m); negative, i.e. damping."""
    waypoint_threshold: float = 0.1
    """Distance (m) to the current waypoint at which the expert moves on to the next one."""
    action_noise: float = 0.5
    """Std of the Gaussian noise added to each action component before clipping to [-1, 1]."""
    waypoint_jitter: float = 0.1
    """Half-width (m) of the uniform jitter added to each intermediate waypoint (cell centre) per
    axis; 0 gives D4RL's exact centres. Keep well below half a corridor (0.4 m at scaling 1)."""
    goal_radius: float = 0.5
    """The goal counts as reached when the ball centre is within this distance (m) of it."""
    goal_noise: float = 0.25
    """Half-width of the uniform noise on the goal position around its cell centre, per axis, as
    a fraction of the cell size (gymnasium-robotics' `position_noise_range`)."""

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise UserError(f"expert.{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise UserError(f"expert.{name} must be a finite number, got {value!r}")
        for name in ("waypoint_threshold", "goal_radius"):
            if getattr(self, name) <= 0:
                raise UserError(f"expert.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("action_noise", "waypoint_jitter", "goal_noise"):
            if getattr(self, name) < 0:
                raise UserError(f"expert.{name} must be >= 0, got {getattr(self, name)!r}")
        if self.goal_noise >= 0.5:
            raise UserError(f"expert.goal_noise must be < 0.5 (a cell), got {self.goal_noise!r}")

    def to_dict(self) -> dict[str, float]:
        """Plain dict of the fields (for metadata)."""
        return {k: float(v) for k, v in asdict(self).items()}


class WaypointExpert:
    """Goal-switching PD waypoint follower over a maze layout (see module docstring).

    Use: `new_goal(x, y)` once, then per step `act(x, y, vx, vy)`, simulate, `update(x', y')`.
    Works on Python floats: it runs once per simulated step, so numpy's per-call overhead on
    2-vectors would dominate the cost of data generation.

    Args:
        layout: `maze_layout(env)` of the maze to drive in.
        config: Gains and noise levels.
        rng: Source of all randomness (goals, jitter, action noise); split into two streams.
    """

    def __init__(self, layout: dict[str, Any], config: ExpertConfig, rng: np.random.Generator):
        self.layout = layout
        self.config = config
        self._goal_rng, self._noise_rng = rng.spawn(2)
        self._scale = float(layout["maze_size_scaling"])
        self._cells: list[Cell] = [(int(i), int(j)) for i, j in layout["free_cells"]]
        self._free = set(self._cells)
        self._dist: dict[Cell, dict[Cell, int]] = {}
        self._noise: list[list[float]] = []
        self._noise_i = 0
        self.goal_cell: Cell | None = None
        self.goal_x = self.goal_y = 0.0
        self._waypoints: list[tuple[float, float]] = []
        self._wp = 0

    @property
    def goal(self) -> np.ndarray:
        """Current goal `[x, y]` (m)."""
        return np.array([self.goal_x, self.goal_y])

    def center(self, cell: Cell) -> tuple[float, float]:
        """Centre `(x, y)` of a cell (the formula of gymnasium-robotics' `cell_rowcol_to_xy`)."""
        x = (cell[1] + 0.5) * self._scale - self.layout["x_map_center"]
        y = self.layout["y_map_center"] - (cell[0] + 0.5) * self._scale
        return x, y

    def cell_of(self, x: float, y: float) -> Cell:
        """Free cell containing `(x, y)`, or the free cell with the nearest centre if none does."""
        cell = layout_cell(self.layout, x, y)
        if cell in self._free:
            return cell
        return min(self._cells, key=lambda c: math.dist(self.center(c), (x, y)))

    def new_goal(self, x: float, y: float) -> None:
        """Draw a random goal away from the ball at `(x, y)` and plan a path to it.

        The goal cell is never the ball's cell nor the previous goal cell (when another exists);
        its position is the cell centre plus uniform noise, redrawn while within `goal_radius`.
        """
        here = self.cell_of(x, y)
        choices = [c for c in self._cells if c != here and c != self.goal_cell]
        if not choices:
            choices = [c for c in self._cells if c != here]
        half = self.config.goal_noise * self._scale
        for _ in range(_GOAL_TRIES):
            cell = choices[int(self._goal_rng.integers(len(choices)))]
            cx, cy = self.center(cell)
            dx, dy = self._goal_rng.uniform(-half, half, size=2).tolist()
            if math.hypot(cx + dx - x, cy + dy - y) > self.config.goal_radius:
                break
        self.goal_cell = cell
        self.goal_x, self.goal_y = cx + dx, cy + dy
        self._plan(here)

    def set_goal(self, x: float, y: float, goal_x: float, goal_y: float) -> None:
        """Head for a given goal `(goal_x, goal_y)` from the ball at `(x, y)`: plan the path of
        cells to it (what `new_goal` does for a random goal; deploy's `expert` agent)."""
        self.goal_cell = self.cell_of(goal_x, goal_y)
        self.goal_x, self.goal_y = float(goal_x), float(goal_y)
        self._plan(self.cell_of(x, y))

    def _plan(self, start: Cell) -> None:
        """Waypoints: jittered centres of the cells after `start` on a shortest path, then goal."""
        dist = self._distances(self.goal_cell)
        path: list[Cell] = []
        cell = start
        while cell != self.goal_cell:
            i, j = cell
            cell = next(
                (i + di, j + dj)
                for di, dj in _MOVES
                if dist.get((i + di, j + dj)) == dist[cell] - 1
            )
            path.append(cell)
        jitter = self.config.waypoint_jitter
        waypoints = []
        for c in path[:-1]:
            cx, cy = self.center(c)
            dx, dy = self._goal_rng.uniform(-jitter, jitter, size=2).tolist() if jitter else (0, 0)
            waypoints.append((cx + dx, cy + dy))
        waypoints.append((self.goal_x, self.goal_y))
        self._waypoints = waypoints
        self._wp = 0

    def _distances(self, goal: Cell) -> dict[Cell, int]:
        """BFS step counts from every reachable free cell to `goal` (cached per goal)."""
        if goal not in self._dist:
            dist = {goal: 0}
            queue = deque([goal])
            while queue:
                i, j = queue.popleft()
                for di, dj in _MOVES:
                    nxt = (i + di, j + dj)
                    if nxt in self._free and nxt not in dist:
                        dist[nxt] = dist[(i, j)] + 1
                        queue.append(nxt)
            if len(dist) != len(self._free):
                raise UserError("the maze has free cells that cannot be reached from each other")
            self._dist[goal] = dist
        return self._dist[goal]

    def act(self, x: float, y: float, vx: float, vy: float) -> tuple[float, float]:
        """Noisy, clipped PD action towards the current waypoint from state `[x, y, vx, vy]`."""
        cfg = self.config
        wx, wy = self._waypoints[self._wp]
        if self._wp < len(self._waypoints) - 1 and math.hypot(wx - x, wy - y) < (
            cfg.waypoint_threshold
        ):
            self._wp += 1
            wx, wy = self._waypoints[self._wp]
        if self._noise_i == len(self._noise):
            block = self._noise_rng.standard_normal((_NOISE_BLOCK, 2)) * cfg.action_noise
            self._noise = block.tolist()
            self._noise_i = 0
        nx, ny = self._noise[self._noise_i]
        self._noise_i += 1
        ax = cfg.p_gain * (wx - x) + cfg.d_gain * vx + nx
        ay = cfg.p_gain * (wy - y) + cfg.d_gain * vy + ny
        return min(1.0, max(-1.0, ax)), min(1.0, max(-1.0, ay))

    def update(self, x: float, y: float) -> bool:
        """After a step that brought the ball to `(x, y)`: if the goal is reached, switch goals.

        Returns:
            True if the goal was reached (and a new one drawn).
        """
        if math.hypot(self.goal_x - x, self.goal_y - y) <= self.config.goal_radius:
            self.new_goal(x, y)
            return True
        return False
