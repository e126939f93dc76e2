"""Device and CPU-thread choices, made in one place for every stage.

Thread counts are a speed choice, never a numerics one, where `pipeline.cpu_math` makes CPU
sums thread-count independent (float32 with MKL); elsewhere `train.threads: auto` stays on one
thread, so a model never depends on the machine's load.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Callable, Iterator
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


def _own_running() -> int:
    """This process's threads that Linux counts as runnable right now (torch's workers
    included: OpenMP threads spin between parallel regions)."""
    running = 0
    for task in Path("/proc/self/task").iterdir():
        try:
            stat = (task / "stat").read_text()
        except OSError:  # the thread ended between listing and reading
            continue
        running += stat[stat.rindex(")") + 2] == "R"
    return running


def runnable_others(samples: int = 5, interval_s: float = 0.01) -> int | None:
    """Runnable threads of other processes right now (the most over a few samples of Linux's
    /proc/loadavg, less this process's runnable threads); None where /proc does not exist."""
    path = Path("/proc/loadavg")
    if not path.exists():
        return None
    most = 0
    for i in range(samples):
        running = int(path.read_text().split()[3].split("/")[0])
        most = max(most, running - _own_running())
        if i + 1 < samples:
            time.sleep(interval_s)
    return most


def _threads_for(others: int | None) -> int:
    return (os.cpu_count() or 1) if others == 0 else 1


def auto_threads(
    setting: int | str | None,
    probe: Callable[[], int | None] | None = None,
    fixed_numerics: bool = True,
) -> int | None:
    """`train.threads`: an int as is; None: torch's default; "auto": every core when no other
    thread is runnable now (`probe`, default `runnable_others`; an idle machine: 2 threads train
    about 1.4x faster than 1), else one (torch's threads on cores that others use wait on each
    other: 20x slower). Logged either way. `AutoThreads` keeps the choice right while a run goes
    on. Where the thread count would change the numbers (`fixed_numerics` False, see
    `numerics_follow_threads`), "auto" is one thread, so a model never depends on the load."""
    if setting != "auto":
        return setting
    if not fixed_numerics:
        log.info("torch threads: 1 (auto; with this dtype and build, threads change the bits)")
        return 1
    others = (probe or runnable_others)()
    threads = _threads_for(others)
    log.info(
        "torch threads: %d (%s runnable elsewhere)", threads, "?" if others is None else others
    )
    return threads


class AutoThreads:
    """`train.threads` for a whole run: the setting's threads from the start, and with "auto"
    a new look every `recheck_s` seconds (`tick` once per step; it reads the clock only).

    A choice made once goes stale: a run that took both cores on an idle machine ran 60x slower
    once another job started (9 s per EM step instead of 0.15). Switching needs the same answer
    twice in a row, so one busy moment does not flip it. Switching is safe only where the
    numbers do not depend on the thread count (float32 with MKL's strict mode,
    `tests/test_config.py`): elsewhere (`fixed_numerics` False) "auto" stays on one thread.
    """

    def __init__(
        self,
        setting: int | str | None,
        recheck_s: float = 10.0,
        probe: Callable[[], int | None] | None = None,
        fixed_numerics: bool = True,
    ):
        if setting == "auto" and not fixed_numerics:
            log.info("torch threads: 1 (auto; with this dtype and build, threads change the bits)")
            setting = 1
        self.setting, self.recheck_s = setting, recheck_s
        self.probe = probe or runnable_others
        self.switches = 0
        self._previous = torch.get_num_threads()
        self._pending: int | None = None
        self._checked = time.monotonic()

    def __enter__(self) -> AutoThreads:
        threads = auto_threads(self.setting, self.probe)
        if threads is not None:
            torch.set_num_threads(threads)
        self._checked = time.monotonic()
        return self

    def __exit__(self, *exc) -> None:
        torch.set_num_threads(self._previous)

    def tick(self) -> None:
        if self.setting != "auto" or time.monotonic() - self._checked < self.recheck_s:
            return
        others = self.probe()
        self._checked = time.monotonic()
        wanted, current = _threads_for(others), torch.get_num_threads()
        if wanted == current:
            self._pending = None
        elif self._pending == wanted:
            torch.set_num_threads(wanted)
            self.switches += 1
            self._pending = None
            log.info("torch threads: %d -> %d (%s runnable elsewhere)", current, wanted, others)
        else:
            self._pending = wanted
