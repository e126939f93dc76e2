"""FLOPs of one replan, counted by PyTorch rather than estimated by hand.

`torch.utils.flop_counter.FlopCounterMode` records every operator that runs and counts the FLOPs
of those it has a formula for: matrix products (`mm`, `addmm`, `bmm`, ...), convolutions and
attention, i.e. the network layers, which is where planning spends its arithmetic. Elementwise
work (activations, normalization, sampling, CEM's sorting) is not counted, so the number is a
lower bound that compares planners by their network evaluations.
"""

from __future__ import annotations

import numpy as np
from torch.utils.flop_counter import FlopCounterMode

from pipeline.planning.agents import Agent


def replan_flops(agent: Agent, state: np.ndarray, goal: np.ndarray, seed: int) -> int:
    """FLOPs of one replan of one environment in `state [sd]` towards `goal [G]`.

    Resets the agent (one slot) first; reset it again before running episodes.
    """
    agent.reset(goal[None], [seed])
    with FlopCounterMode(display=False) as counter:
        agent.replan(np.array([0]), state[None])
    return int(counter.get_total_flops())
