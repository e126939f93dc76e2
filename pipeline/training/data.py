"""Window batches on the training device, gathered by index from episodes stored once."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.errors import UserError
from pipeline.segments import Segments


@dataclass
class WindowBatch:
    """Normalized sub-trajectories tau_T.

    Attributes:
        states: `[B, T + 1, sd]` s_0..s_T.
        actions: `[B, T, ad]` a_0..a_{T-1}.
        after_states: `[B, (K - 1) T, sd]` s_{T+1}..s_{KT}: the K - 1 windows that follow, for
            a TAWM trained to chain K skills (`train.tawm_chain`); None for one window.
        after_actions: `[B, (K - 1) T, ad]` a_T..a_{KT-1}, or None.
    """

    states: torch.Tensor
    actions: torch.Tensor
    after_states: torch.Tensor | None = None
    after_actions: torch.Tensor | None = None


class WindowSampler:
    """Uniformly samples windows of one split (with replacement), as the paper does.

    The normalized episodes live on `device` once; a batch is two gathers. Sampling draws from
    its own `torch.Generator` (seeded), whose state is saved for resume.

    With `chain` K > 1 (`train.tawm_chain`) each draw is a window followed by K - 1 more of the
    same episode, end to end (`WindowBatch.after_states`): only the windows that K - 1 windows
    of the split follow are drawn.

    Raises:
        UserError: no window of the split is followed by K - 1 more (episodes too short).
    """

    def __init__(
        self, segments: Segments, split: str, device: torch.device, seed: int, chain: int = 1
    ):
        stats = segments.stats
        states = (segments.states - stats.state_mean) / stats.state_std
        actions = (segments.actions - stats.action_mean) / stats.action_std
        self.states = torch.as_tensor(states, dtype=torch.float32, device=device)
        self.actions = torch.as_tensor(actions, dtype=torch.float32, device=device)
        self.window = segments.window
        starts = segments.starts[split] if chain == 1 else chained_starts(segments, split, chain)
        self.starts = torch.as_tensor(starts, dtype=torch.long, device=device)
        self.offsets = torch.arange(segments.window + (chain - 1) * segments.horizon, device=device)
        self.generator = torch.Generator().manual_seed(seed)
        self.device = device

    def __len__(self) -> int:
        return int(self.starts.numel())

    def gather(self, idx: torch.Tensor) -> WindowBatch:
        """Windows at positions `idx [B]` of this split (with those that follow them)."""
        steps = self.starts[idx.to(self.device, non_blocking=True)][:, None] + self.offsets
        states, actions = self.states[steps], self.actions[steps[:, :-1]]
        if len(self.offsets) == self.window:
            return WindowBatch(states, actions)
        t = self.window - 1
        return WindowBatch(
            states[:, : t + 1], actions[:, :t], states[:, t + 1 :], actions[:, t:]
        )  # fmt: skip

    def sample(self, batch_size: int) -> WindowBatch:
        """`batch_size` windows drawn uniformly.

        The indices come from the CPU generator (the same stream on every device, and resume
        states that any device can load); on CUDA they travel from pinned memory without a
        host synchronization.
        """
        idx = torch.randint(len(self), (batch_size,), generator=self.generator)
        if self.device.type == "cuda":
            idx = idx.pin_memory().to(self.device, non_blocking=True)
        return self.gather(idx)

    def fixed_subset(self, n: int, seed: int) -> np.ndarray:
        """Positions of `n` windows (or all) chosen once, for repeatable validation."""
        if n >= len(self):
            return np.arange(len(self))
        return np.sort(np.random.default_rng(seed).choice(len(self), size=n, replace=False))


def chained_starts(segments: Segments, split: str, chain: int) -> np.ndarray:
    """The window starts of `split` that `chain - 1` windows of the split follow end to end
    in the same episode (a window's last state is the next one's first).

    Raises:
        UserError: none does.
    """
    starts = segments.starts[split]
    t = segments.horizon
    episode = np.searchsorted(segments.episode_offsets, starts, side="right")
    keep = np.ones(len(starts), dtype=bool)
    for j in range(1, chain):
        later = starts + j * t
        found = np.isin(later, starts)
        same = np.searchsorted(segments.episode_offsets, later, side="right") == episode
        keep &= found & same
    if not keep.any():
        raise UserError(
            f"train.tawm_chain={chain}: no {split} window of {segments.window} states is followed "
            f"by {chain - 1} more in its episode; lower train.tawm_chain or segment.window"
        )
    return starts[keep]
