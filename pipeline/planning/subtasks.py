"""One object at a time (`deploy.object_subtasks`): a goal of several objects as a sequence of
one-object goals.

The planner's cost is the distance to the whole goal. With two cubes to move, the candidate
plans that move the first cube and those that move the second lower it alike, and CEM's elites,
drawn from both, may average to a plan that moves neither. Here each replan's target is one
object's goal (on cube-double-play it changed nothing: results/manipulation.md):

- **Objects** are groups of goal dims (`ManipSpaceSpec.goal_objects`: each cube's position, each
  button, the drawer, the window), each with its success tolerance (the goal cost's `scale`): an
  object is done when its scaled distance to its goal is at most 1, OGBench's rule per object.
- **The active object** is the first one, in the goal's order, that is not done, judged from the
  state the replan starts from. Nothing is remembered between replans: an object knocked out of
  its goal becomes active again when it comes first.
- **The target** is the goal for the active object and for the objects already done (keep them
  there), and the current value of every object still to come (leave it where it is). When every
  object is done, the target is the goal.

Not the paper's (it plans to the whole goal, `false`). The goal's order decides the sequence: a
cube stacked on another comes after it in OGBench's tasks, but a swap (each cube's goal where the
other stands) has no order that works one move at a time, and the scene's drawer, locked by a
button whose goal state is locked, needs the button first undone: objects whose goals interact
are planned as a whole.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch


class ObjectSubtasks:
    """Each replan's target for one object at a time (see the module docstring).

    Args:
        objects: The goal vector's indices of each object, in the goal's order; together every
            index once.
        scale: Per goal dim, the success tolerance its distance is divided by.
    """

    def __init__(self, objects: Sequence[Sequence[int]], scale: Sequence[float]):
        flat = sorted(i for obj in objects for i in obj)
        if not objects or any(not obj for obj in objects) or flat != list(range(len(scale))):
            raise ValueError(
                f"objects must cover the {len(scale)} goal dims once each, got {objects}"
            )
        if not all(v > 0 for v in scale):
            raise ValueError(f"scale must be positive, got {scale}")
        self.objects = tuple(tuple(int(i) for i in obj) for obj in objects)
        self.scale = tuple(float(v) for v in scale)
        # [O, G]: which goal dims belong to each object
        self._members = torch.zeros(len(self.objects), len(self.scale))
        for o, obj in enumerate(self.objects):
            self._members[o, list(obj)] = 1.0

    def done(self, current: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """`[A, O]`: each object within its tolerance, from `current [A, G]` (the state's goal
        dims) and `goals [A, G]`."""
        scale = torch.tensor(self.scale, dtype=current.dtype, device=current.device)
        squared = ((current - goals) / scale) ** 2  # [A, G]
        return squared @ self._members.to(current).T <= 1.0  # [A, O]

    def active(self, current: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """`[A]`: the index of each row's first object not done, or O where all are done."""
        return self._first_pending(self.done(current, goals))

    def _first_pending(self, done: torch.Tensor) -> torch.Tensor:
        pending = ~done  # [A, O]
        first = pending.to(torch.int8).argmax(dim=-1)  # the first True (0 where none)
        return torch.where(pending.any(dim=-1), first, len(self.objects))

    def targets(self, current: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        """`[A, G]`: the goal for the active object and every object done, the current value
        for the objects still to come after it; the goal itself where every object is done."""
        done = self.done(current, goals)  # [A, O]
        active = self._first_pending(done)  # [A]
        order = torch.arange(len(self.objects), device=current.device)
        to_come = ~done & (order[None, :] > active[:, None])  # [A, O]: after the active one
        leave = to_come.to(current.dtype) @ self._members.to(current) > 0  # [A, G]
        return torch.where(leave, current, goals)
