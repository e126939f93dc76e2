"""Device and CPU-thread choices, made in one place for every stage."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

from pipeline.errors import UserError


def resolve_device(device: str, key: str) -> torch.device:
    """`auto` -> CUDA if available, else CPU; `cuda` without a GPU is a `UserError` naming `key`."""
    if device == "cuda" and not torch.cuda.is_available():
        raise UserError(f"{key} is cuda but no CUDA GPU is available; use auto or cpu")
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    return torch.device(device)


@contextlib.contextmanager
def torch_threads(threads: int | None) -> Iterator[None]:
    """Run torch on `threads` intra-op CPU threads for a while (None: leave torch's default).

    Our CPU work is small networks on small batches: with 2 threads on 2 cores shared with other
    jobs, torch's threads wait on each other (measured: 1000 dynamics steps 10.4 s with 2
    threads, 4.7 s with 1, at load 2.9; EM training 0.41 steps/s with 2 threads, 7.7 with 1).
    """
    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
