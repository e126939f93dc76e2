"""Waypoints from a graph of the demonstrations' skills (`deploy.subgoals`).

The planner's cost is the distance to the goal. Where a wall stands between the agent and the
goal and the way round is longer than a plan of L skills reaches, that cost has a local minimum on
the near side of the wall: every replan presses towards it (results/ogbench-point.md, tasks 3-5).
The graph gives the planner a nearer target that leads round.

- **Nodes:** the occupied cells of a grid (side `cell`) over the goal dimensions of the train
  split's states, each at the mean position of its states.
- **Edges:** every training window links the node of its first state with the node of its last
  state: one skill of the data, T steps. Links go both ways, because the mazes are reversible.
  A window in which one step moves farther than a cell is no edge: that is not a skill the agent
  steers but a jump the world makes (OGBench's teleports, which are random, one-way, and in a
  third of the cases end in a closed cell; a reset). Data without such jumps keeps every window.
- **Distances:** the fewest skills between any two nodes, by breadth-first search (scipy).
- **Each replan, per environment:**
  - When the goal's node is at most `reach` skills away, or not connected at all, the target is
    the goal itself.
  - Otherwise the target is the node within `reach` skills of the agent's node that is fewest
    skills from the goal's node; among equals, the one nearest the goal.
  - The agent's and the goal's nodes are the nearest ones in the goal dimensions.
- **Line of sight** (`line_of_sight`): a goal two skills away may still lie round a wall, and a
  waypoint too (results/ogbench-point.md, large-stitch task 2). With it, a straight line counts as
  clear when every grid cell it crosses is one the data visits (walls are never visited). The goal
  is then the target only when it is within `reach` and in sight of the agent (or in the agent's
  own node), and the waypoint is the best node in sight of the agent's node, when one is fewer
  skills from the goal than the agent's node; otherwise the rule above.

**Only when stuck** (`patience`, `StuckWatch`): an episode plans to the goal itself, as the
paper does, until it has gone `patience` replans without getting `progress` closer to the goal
than ever before; from then on, to the graph's waypoints. Episodes that never meet a wall's local
minimum keep the paper's plans.

Only the offline data is used: no maze layout and no simulator. This resembles "search on the
replay buffer" (Eysenbach et al., 2019), with the data's own skills as edges.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import shortest_path

from pipeline.segments import Segments


class SubgoalGraph:
    """Skill-hop distances between the cells the demonstrations visit, and waypoints from them.

    Args:
        nodes: `[M, G]` node positions (goal dimensions).
        hops: `[M, M]` fewest skills between nodes (inf: not connected).
        reach: Skills ahead a waypoint may be (at most the plan's L).
    """

    def __init__(
        self,
        nodes: np.ndarray,
        hops: np.ndarray,
        reach: int,
        device: torch.device,
        sight: Occupancy | None = None,
    ):
        if reach < 1:
            raise ValueError(f"reach must be >= 1, got {reach}")
        self.nodes = torch.as_tensor(nodes, dtype=torch.float32, device=device)
        self.hops = torch.as_tensor(hops, dtype=torch.float32, device=device)
        self.reach = reach
        self.sight = sight
        self.visible = None  # [M, M]: node pairs within reach with a clear line between them
        if sight is not None:
            pairs = torch.nonzero(self.hops <= reach)
            clear = torch.cat([
                sight.clear(self.nodes[chunk[:, 0]], self.nodes[chunk[:, 1]])
                for chunk in pairs.split(4096)
            ])  # fmt: skip
            self.visible = torch.zeros_like(self.hops, dtype=torch.bool)
            self.visible[pairs[:, 0], pairs[:, 1]] = clear

    @classmethod
    def from_windows(
        cls,
        points: np.ndarray,
        first: np.ndarray,
        last: np.ndarray,
        cell: float,
        reach: int,
        device: torch.device | str = "cpu",
        *,
        line_of_sight: bool,
    ) -> SubgoalGraph:
        """Graph of the positions `points [N, G]` the data visits (in order, episode after
        episode) and its windows, each from point `first[w]` to point `last[w]` (`[W]` indices
        into `points`, within one episode); windows with a jump (module docstring) are left out."""
        if cell <= 0:
            raise ValueError(f"cell must be > 0, got {cell}")
        if len(first) == 0:
            raise ValueError("no windows to build a subgoal graph from")
        cells, node_of = np.unique(np.floor(points / cell).astype(np.int64), axis=0,
                                   return_inverse=True)  # fmt: skip
        node_of = node_of.reshape(-1)
        m = len(cells)
        nodes = np.zeros((m, points.shape[1]))
        np.add.at(nodes, node_of, points)
        nodes /= np.bincount(node_of, minlength=m)[:, None]
        a, b = node_of[first], node_of[last]
        step = np.linalg.norm(np.diff(points, axis=0), axis=1)
        jumps = np.concatenate([[0], np.cumsum(step > cell)])  # jumps before each point
        keep = (a != b) & (jumps[last] == jumps[first])
        adjacency = coo_matrix((np.ones(int(keep.sum())), (a[keep], b[keep])), shape=(m, m))
        hops = shortest_path(adjacency.tocsr(), method="D", directed=False, unweighted=True)
        sight = Occupancy(cells, cell, torch.device(device)) if line_of_sight else None
        return cls(nodes, hops, reach, torch.device(device), sight)

    @classmethod
    def from_segments(
        cls,
        segments: Segments,
        dims: tuple[int, ...],
        cell: float,
        reach: int,
        device: torch.device | str = "cpu",
        *,
        line_of_sight: bool,
    ) -> SubgoalGraph:
        """Graph of the train split's states and windows (positions: state dimensions `dims`)."""
        offsets = segments.episode_offsets
        steps = np.concatenate(
            [np.arange(offsets[e], offsets[e + 1]) for e in segments.episodes_in("train")]
            or [np.zeros(0, np.int64)]
        )
        where = np.full(len(segments.states), -1, dtype=np.int64)  # global step -> point
        where[steps] = np.arange(len(steps))
        starts = segments.starts["train"]
        points = segments.states[steps][:, list(dims)].astype(np.float64)
        first, last = where[starts], where[starts + segments.window - 1]
        return cls.from_windows(
            points, first, last, cell, reach, device, line_of_sight=line_of_sight
        )

    def nearest(self, positions: torch.Tensor) -> torch.Tensor:
        """`[B]` index of the node nearest each of `positions [B, G]`."""
        return torch.cdist(positions, self.nodes).argmin(dim=-1)

    def waypoints(self, positions: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """Targets `[B, G]` for agents at `positions [B, G]` heading to `goals [B, G]`."""
        ahead = torch.cdist(goals, self.nodes)  # [B, M]: each node's distance to each goal
        here, there = self.nearest(positions), ahead.argmin(dim=-1)
        to_goal = self.hops[:, there].T  # [B, M]: skills from each node to each goal's node
        within = self.hops[here] <= self.reach  # [B, M]
        tie = 1e-3 * ahead / (1.0 + ahead.max())
        best = (torch.where(within, to_goal, torch.inf) + tie).argmin(dim=-1)
        direct = self.hops[here, there]
        near = direct <= self.reach
        if self.sight is not None:  # the goal only in sight; a waypoint in sight when one helps
            seen = within & self.visible[here]
            best_seen = (torch.where(seen, to_goal, torch.inf) + tie).argmin(dim=-1)
            closer = to_goal.gather(1, best_seen[:, None])[:, 0] < direct
            best = torch.where(closer, best_seen, best)
            near = (direct == 0) | (near & self.sight.clear(positions, goals))
        use_goal = near | ~torch.isfinite(direct)
        return torch.where(use_goal[:, None], goals, self.nodes[best])


class Occupancy:
    """The grid cells (side `cell`) that the data visits, for line-of-sight tests.

    Args:
        cells: `[C, G]` integer indices of the visited cells (`floor(position / cell)`).
        cell: Grid side, in the positions' units.
    """

    def __init__(self, cells: np.ndarray, cell: float, device: torch.device):
        lo = cells.min(axis=0)
        shape = cells.max(axis=0) - lo + 1
        grid = np.zeros(shape, dtype=bool)
        grid[tuple((cells - lo).T)] = True
        self.cell = float(cell)
        self.grid = torch.as_tensor(grid.reshape(-1), device=device)
        self.lo = torch.as_tensor(lo, device=device)
        self.shape = torch.as_tensor(shape, device=device)
        strides = np.cumprod(np.concatenate([shape[1:], [1]])[::-1])[::-1]
        self.strides = torch.as_tensor(strides.copy(), device=device)
        # Samples along a line: a quarter cell apart over the grid's diagonal (fixed: no sync).
        diagonal = float(np.linalg.norm(shape)) * 4
        self.t = torch.linspace(0.0, 1.0, int(np.ceil(diagonal)) + 2, device=device)

    def clear(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """`[N]`: whether the straight line from each of `a [N, G]` to `b [N, G]` crosses only
        visited cells (a point outside the grid is not visited)."""
        points = a[:, None] + self.t[None, :, None] * (b - a)[:, None]  # [N, S, G]
        index = torch.floor(points / self.cell).long() - self.lo
        inside = ((index >= 0) & (index < self.shape)).all(dim=-1)
        flat = (torch.minimum(index.clamp(min=0), self.shape - 1) * self.strides).sum(dim=-1)
        return (inside & self.grid[flat]).all(dim=-1)


class StuckWatch:
    """Per environment slot, whether its episode has stopped getting closer to its goal.

    At each replan a slot's goal distance is compared with the best it has had this episode: a
    distance at least `progress` below it is progress. A slot that has gone `patience` replans
    without progress is stuck, and stays so until its episode ends (`reset`).

    Args:
        patience: Replans without progress before a slot counts as stuck.
        progress: The least improvement on the best distance that counts as progress.
    """

    def __init__(self, patience: int, progress: float):
        if patience < 1:
            raise ValueError(f"patience must be >= 1, got {patience}")
        if progress <= 0:
            raise ValueError(f"progress must be > 0, got {progress}")
        self.patience = patience
        self.progress = progress
        self.best = torch.zeros(0)  # [B] best goal distance so far
        self.since = torch.zeros(0, dtype=torch.long)  # [B] replans since the last progress
        self.stuck = torch.zeros(0, dtype=torch.bool)  # [B]

    def reset(self, slots: int, device: torch.device | str) -> None:
        """New episodes in all `slots`: none stuck, no best distance yet."""
        self.best = torch.full((slots,), torch.inf, device=device)
        self.since = torch.zeros(slots, dtype=torch.long, device=device)
        self.stuck = torch.zeros(slots, dtype=torch.bool, device=device)

    def update(self, rows: torch.Tensor, distance: torch.Tensor) -> torch.Tensor:
        """Record the goal `distance [A]` of slots `rows [A]` at a replan; `[A]` whether each is
        stuck now."""
        best = self.best[rows]
        better = distance <= best - self.progress
        self.best[rows] = torch.where(better, distance, best)
        since = torch.where(better, torch.zeros_like(self.since[rows]), self.since[rows] + 1)
        self.since[rows] = since
        stuck = self.stuck[rows] | (since >= self.patience)
        self.stuck[rows] = stuck
        return stuck
