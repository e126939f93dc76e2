"""Window batches on the training device, gathered by index from episodes stored once."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pipeline.segments import Segments


@dataclass
class WindowBatch:
    """Normalized sub-trajectories tau_T.

    Attributes:
        states: `[B, T + 1, sd]` s_0..s_T.
        actions: `[B, T, ad]` a_0..a_{T-1}.
    """

    states: torch.Tensor
    actions: torch.Tensor


class WindowSampler:
    """Uniformly samples windows of one split (with replacement), as the paper does.

    The normalized episodes live on `device` once; a batch is two gathers. Sampling draws from
    its own `torch.Generator` (seeded), whose state is saved for resume.
    """

    def __init__(self, segments: Segments, split: str, device: torch.device, seed: int):
        stats = segments.stats
        states = (segments.states - stats.state_mean) / stats.state_std
        actions = (segments.actions - stats.action_mean) / stats.action_std
        self.states = torch.as_tensor(states, dtype=torch.float32, device=device)
        self.actions = torch.as_tensor(actions, dtype=torch.float32, device=device)
        self.starts = torch.as_tensor(segments.starts[split], dtype=torch.long, device=device)
        self.offsets = torch.arange(segments.window, device=device)
        self.generator = torch.Generator().manual_seed(seed)
        self.device = device

    def __len__(self) -> int:
        return int(self.starts.numel())

    def gather(self, idx: torch.Tensor) -> WindowBatch:
        """Windows at positions `idx [B]` of this split."""
        steps = self.starts[idx.to(self.device, non_blocking=True)][:, None] + self.offsets
        return WindowBatch(self.states[steps], self.actions[steps[:, :-1]])

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
