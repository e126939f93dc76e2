"""Waypoints from a graph of the demonstrations' skills (`deploy.subgoals`).

The planner's cost is the distance to the goal. Where a wall stands between the agent and the
goal and the way round is longer than a plan of L skills reaches, that cost has a local minimum on
the near side of the wall: every replan presses towards it (results/ogbench.md, tasks 3-5). The
graph gives the planner a nearer target that leads round.

- **Nodes:** the occupied cells of a grid (side `cell`) over the goal dimensions of the train
  split's states, each at the mean position of its states.
- **Edges:** every training window links the node of its first state with the node of its last
  state: one skill of the data, T steps. Links go both ways, because the mazes are reversible.
- **Distances:** the fewest skills between any two nodes, by breadth-first search (scipy).
- **Each replan, per environment:**
  - When the goal's node is at most `reach` skills away, or not connected at all, the target is
    the goal itself.
  - Otherwise the target is the node within `reach` skills of the agent's node that is fewest
    skills from the goal's node; among equals, the one nearest the goal.
  - The agent's and the goal's nodes are the nearest ones in the goal dimensions.

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

    def __init__(self, nodes: np.ndarray, hops: np.ndarray, reach: int, device: torch.device):
        if reach < 1:
            raise ValueError(f"reach must be >= 1, got {reach}")
        self.nodes = torch.as_tensor(nodes, dtype=torch.float32, device=device)
        self.hops = torch.as_tensor(hops, dtype=torch.float32, device=device)
        self.reach = reach

    @classmethod
    def from_windows(
        cls,
        points: np.ndarray,
        first: np.ndarray,
        last: np.ndarray,
        cell: float,
        reach: int,
        device: torch.device | str = "cpu",
    ) -> SubgoalGraph:
        """Graph of the positions `points [N, G]` the data visits and its windows, each from
        point `first[w]` to point `last[w]` (`[W]` indices into `points`)."""
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
        keep = a != b
        adjacency = coo_matrix((np.ones(int(keep.sum())), (a[keep], b[keep])), shape=(m, m))
        hops = shortest_path(adjacency.tocsr(), method="D", directed=False, unweighted=True)
        return cls(nodes, hops, reach, torch.device(device))

    @classmethod
    def from_segments(
        cls,
        segments: Segments,
        dims: tuple[int, ...],
        cell: float,
        reach: int,
        device: torch.device | str = "cpu",
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
        return cls.from_windows(points, first, last, cell, reach, device)

    def nearest(self, positions: torch.Tensor) -> torch.Tensor:
        """`[B]` index of the node nearest each of `positions [B, G]`."""
        return torch.cdist(positions, self.nodes).argmin(dim=-1)

    def waypoints(self, positions: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """Targets `[B, G]` for agents at `positions [B, G]` heading to `goals [B, G]`."""
        ahead = torch.cdist(goals, self.nodes)  # [B, M]: each node's distance to each goal
        here, there = self.nearest(positions), ahead.argmin(dim=-1)
        to_goal = self.hops[:, there].T  # [B, M]: skills from each node to each goal's node
        within = self.hops[here] <= self.reach  # [B, M]
        score = torch.where(within, to_goal, torch.inf) + 1e-3 * ahead / (1.0 + ahead.max())
        best = score.argmin(dim=-1)
        direct = self.hops[here, there]
        use_goal = (direct <= self.reach) | ~torch.isfinite(direct)
        return torch.where(use_goal[:, None], goals, self.nodes[best])
