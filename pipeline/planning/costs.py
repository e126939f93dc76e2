"""Task costs over predicted state sequences (the planner only ever sees predictions, paper §3)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch


class GoalCost:
    """Goal reaching as in the paper's maze2d experiments (§4.2): the cost of a predicted sequence
    is the L2 distance between the goal and the predicted state nearest to it.

    Which state dims the goal gives (`dims`) and a per-dim `scale` make the same cost serve any
    goal: the distance is over `(state[dims] - goal) / scale`, so with each dim's scale its
    success tolerance (OGBench's manipulation: a cube's 0.04 m is 0.4 observation units) a cost
    of 1 is "at the tolerance" whatever the dims measure. No scale (the mazes): raw units, the
    paper's cost exactly.

    Sparse: one value per plan, whichever skill gets closest; no per-step reward. The current state
    s_0 is not a prediction and is left out, so every candidate is scored by where it leads.

    With `skill_penalty` > 0 the distance after skill k (1..L) counts `skill_penalty * k` more:
    of two plans that get equally close, the one that gets there sooner wins. The paper's cost
    (0) is indifferent to when: a plan of L skills to a target one skill away may dawdle.

    With `fallen` (a test of predicted states, e.g. the ant's torso down or upside down) a plan
    whose predicted states include a fallen one costs `fall_penalty` more: a flipped ant cannot
    right itself, however near the goal it lies.

    Args:
        goals: `[B, G]` one goal per problem of the planning batch (e.g. `[x, y]`).
        dims: The state dimensions the goal is compared with (default: the first G).
        scale: G positive divisors, one per goal dim (numbers, not a tensor: they are part of
            `key`), or None (raw units).
        skill_penalty: Goal units added per skill before the nearest state (0: the paper).
        fall_penalty: Goal units added to a plan predicted to fall (needs `fallen`).
        fallen: `states [..., sd] -> bool [...]`, or None (the agent cannot fall).
    """

    def __init__(
        self,
        goals: torch.Tensor,
        dims: tuple[int, ...] | None = None,
        skill_penalty: float = 0.0,
        fall_penalty: float = 0.0,
        fallen: Callable[[torch.Tensor], torch.Tensor] | None = None,
        scale: Sequence[float] | None = None,
    ):
        self.goals = goals
        self.dims = tuple(dims) if dims is not None else tuple(range(goals.shape[-1]))
        if len(self.dims) != goals.shape[-1]:
            raise ValueError(f"goal has {goals.shape[-1]} dims but dims={self.dims}")
        self.scale_values = None if scale is None else tuple(float(v) for v in scale)
        if self.scale_values is not None and (
            len(self.scale_values) != len(self.dims) or not all(v > 0 for v in self.scale_values)
        ):
            raise ValueError(f"scale must be {len(self.dims)} positive numbers, got {scale}")
        self.scale = None  # [G] on the goals' device
        if self.scale_values is not None:
            self.scale = torch.tensor(self.scale_values, dtype=goals.dtype, device=goals.device)
        if skill_penalty < 0:
            raise ValueError(f"skill_penalty must be >= 0, got {skill_penalty}")
        self.skill_penalty = float(skill_penalty)
        if fall_penalty < 0:
            raise ValueError(f"fall_penalty must be >= 0, got {fall_penalty}")
        self.fall_penalty = float(fall_penalty) if fallen is not None else 0.0
        self.fallen = fallen

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        """Predicted `states [B, K, L + 1, sd]` (0: s_0) of the B problems -> `[B, K]`."""
        distance = self.per_skill(states)  # [B, K, L]
        if self.skill_penalty:
            k = torch.arange(1, distance.shape[-1] + 1, device=distance.device)
            distance = distance + self.skill_penalty * k.to(distance.dtype)
        cost = distance.amin(dim=-1)
        if self.fall_penalty:
            falls = self.fallen(states[:, :, 1:]).any(dim=-1)  # [B, K]
            cost = cost + self.fall_penalty * falls.to(cost.dtype)
        return cost

    def per_skill(self, states: torch.Tensor) -> torch.Tensor:
        """`[B, K, L]`: the goal distance after each skill of `states [B, K, L + 1, sd]`."""
        reached = _select(states[:, :, 1:], self.dims)  # [B, K, L, G]
        residual = reached - self.goals[:, None, None, :]
        if self.scale is not None:
            residual = residual / self.scale
        return torch.linalg.vector_norm(residual, dim=-1)

    @property
    def key(self) -> tuple:
        """What a captured plan depends on besides the goals' values: dims, penalties, fall test
        and (when there is one) the scale."""
        key = (self.dims, self.skill_penalty, self.fall_penalty, self.fallen)
        return key if self.scale_values is None else (*key, self.scale_values)

    def with_goals(self, goals: torch.Tensor) -> GoalCost:
        """The same cost with other goals `[B', G]` (e.g. a CUDA graph's static input)."""
        return GoalCost(
            goals, self.dims, self.skill_penalty, self.fall_penalty, self.fallen, self.scale_values
        )


class ValueGoalCost(GoalCost):
    """`GoalCost` plus a learned temporal distance to the goal after each skill: the distance
    after skill k (1..L) counts `weight * (k + d(s_k, g) / skill_steps)` more, where
    `d(s, g)` is the steps to go a goal-conditioned value gives (`pipeline.value`), so the cost
    is the plan's estimated skills to the goal when it goes through s_k. A short plan is then
    scored by where it leads however far the goal is, and the TAWM need not be chained to the
    goal. `weight` 0 is `GoalCost` (the paper's cost).

    Args:
        steps_to_go: `(states [..., sd], goals [..., G]) -> [...]` steps to the goal.
        weight: Goal units (success tolerances on manipulation) per skill to go.
        skill_steps: Environment steps per skill (T).
        Others: as `GoalCost` (without a fall test).
    """

    def __init__(
        self,
        goals: torch.Tensor,
        steps_to_go: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
        weight: float,
        skill_steps: int,
        dims: tuple[int, ...] | None = None,
        skill_penalty: float = 0.0,
        scale: Sequence[float] | None = None,
    ):
        super().__init__(goals, dims, skill_penalty, scale=scale)
        if weight < 0 or skill_steps < 1:
            raise ValueError(f"need weight >= 0, skill_steps >= 1; got {weight}, {skill_steps}")
        self.steps_to_go = steps_to_go
        self.weight = float(weight)
        self.skill_steps = int(skill_steps)

    def per_skill(self, states: torch.Tensor) -> torch.Tensor:
        distance = super().per_skill(states)  # [B, K, L]
        if not self.weight:
            return distance
        b, k, n = distance.shape
        goals = self.goals[:, None, None, :].expand(b, k, n, -1)
        to_go = self.steps_to_go(states[:, :, 1:], goals) / self.skill_steps
        skills = torch.arange(1, n + 1, device=distance.device, dtype=distance.dtype)
        return distance + self.weight * (skills + to_go)

    @property
    def key(self) -> tuple:
        return (*super().key, self.steps_to_go, self.weight, self.skill_steps)

    def with_goals(self, goals: torch.Tensor) -> ValueGoalCost:
        return ValueGoalCost(
            goals, self.steps_to_go, self.weight, self.skill_steps, self.dims,
            self.skill_penalty, self.scale_values,
        )  # fmt: skip


def _select(x: torch.Tensor, dims: tuple[int, ...]) -> torch.Tensor:
    """`x[..., dims]`, as a slice when the dims are consecutive (a view, no gather)."""
    if dims == tuple(range(dims[0], dims[0] + len(dims))):
        return x[..., dims[0] : dims[0] + len(dims)]
    return x[..., list(dims)]
