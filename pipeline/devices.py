"""Device and CPU-thread choices, made in one place for every stage."""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path

import torch

from pipeline.errors import UserError

log = logging.getLogger(__name__)


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


def runnable_others(samples: int = 5, interval_s: float = 0.05) -> int | None:
    """Other runnable threads on this machine right now (the most over a few samples of Linux's
    /proc/loadavg, less this process); None where that file does not exist."""
    path = Path("/proc/loadavg")
    if not path.exists():
        return None
    most = 0
    for i in range(samples):
        running = int(path.read_text().split()[3].split("/")[0])
        most = max(most, running - 1)  # the reading process itself is running
        if i + 1 < samples:
            time.sleep(interval_s)
    return most


def auto_threads(setting: int | str | None) -> int | None:
    """`train.threads`: an int as is; None: torch's default; "auto": every core when no other
    thread is runnable as training starts (an idle machine: 2 threads train about 1.5x faster
    than 1), else one (torch's threads on cores that others use wait on each other: 20x
    slower). Logged either way."""
    if setting != "auto":
        return setting
    others = runnable_others()
    threads = (os.cpu_count() or 1) if others == 0 else 1
    log.info(
        "torch threads: %d (%s runnable elsewhere)", threads, "?" if others is None else others
    )
    return threads
