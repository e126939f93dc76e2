"""Reproducible CPU arithmetic: the same bits whatever the thread count or the machine's load.

Torch multiplies float32 matrices on CPU with Intel MKL, which by default splits long sums
between threads: the same EM update gave different bits on 1 and 2 threads (a weight gradient
sums over batch x window rows), so a model depended on how busy the machine was. MKL's strict
conditional numerical reproducibility (CNR, `MKL_CBWR=<branch>,STRICT`) fixes the order of
every sum whatever the thread count. The branch is the widest instruction set every CPU of its
kind has: `AVX512` where the CPU has AVX-512 (so Intel Xeons of different generations give the
same bits; measured no slower than MKL's own choice), else `AVX2` (about 1.8x slower than
AVX-512 on a CPU that has both, so never chosen there). MKL takes a named branch only on Intel
CPUs: on AMD's it runs `AUTO,STRICT` whatever the branch asked (read back on an EPYC of the
Zen 4 generation), the same bits on any thread count there but not Intel's; so `default_mode`
asks for that on every other vendor's CPU.

MKL reads `MKL_CBWR` once, at its first call: `set_default_environment` (called by
`pipeline/__init__.py`, before any matrix product) sets it unless the user did; `ensure` reads
back the mode in force and sets it through MKL's service function where a process did matrix
products before importing `pipeline`. Not covered: bfloat16 on CPU (oneDNN's kernels) and torch
builds without MKL; `numerics_follow_threads` names those, and `train.threads: auto` then stays
on one thread. This module imports torch only inside the functions that need it.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)

# mkl_service.h: the branch codes of MKL's CNR modes and the strict flag
_BRANCHES = {2: "AUTO", 3: "COMPATIBLE", 4: "SSE2", 6: "SSSE3", 7: "SSE4_1", 8: "SSE4_2",
             9: "AVX", 10: "AVX2", 11: "AVX512_MIC", 12: "AVX512", 13: "AVX512_MIC_E1",
             14: "AVX512_E1"}  # fmt: skip
_CODES = {name: code for code, name in _BRANCHES.items()}
_STRICT, _ALL = 0x10000, -1


def default_mode(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """On an Intel CPU (Linux's `GenuineIntel`), `AVX512,STRICT` with AVX-512 (the `avx512f`
    flag), else `AVX2,STRICT` with AVX2; `AUTO,STRICT` (MKL's choice) elsewhere: on other
    vendors' CPUs, where MKL runs that whatever branch it is given, and where /proc/cpuinfo does
    not exist."""
    try:
        flags = set(cpuinfo.read_text(errors="replace").split())
    except OSError:
        return "AUTO,STRICT"
    if "GenuineIntel" not in flags:
        return "AUTO,STRICT"
    for flag, branch in (("avx512f", "AVX512"), ("avx2", "AVX2")):
        if flag in flags:
            return f"{branch},STRICT"
    return "AUTO,STRICT"


def set_default_environment() -> None:
    """`MKL_CBWR` = `default_mode()` for this process and its children, unless already set."""
    os.environ.setdefault("MKL_CBWR", default_mode())


@functools.cache
def _mkl() -> ctypes.CDLL | None:
    """Torch's statically linked MKL service functions, or None (a build without MKL)."""
    import torch

    try:
        mkl = ctypes.CDLL(str(Path(torch.__file__).parent / "lib" / "libtorch_cpu.so"))
        for name in ("mkl_serv_cbwr_get", "mkl_serv_cbwr_set"):
            getattr(mkl, name).restype = ctypes.c_int
            getattr(mkl, name).argtypes = [ctypes.c_int]
    except (OSError, AttributeError):
        return None
    return mkl


def mode() -> str | None:
    """MKL's reproducibility mode in force, e.g. "AVX512,STRICT" (STRICT: the same bits on any
    thread count); "off" when MKL runs without one; None where torch has no MKL."""
    mkl = _mkl()
    if mkl is None:
        return None
    value = mkl.mkl_serv_cbwr_get(_ALL)
    branch = _BRANCHES.get(value & 0xFFFF)
    if branch is None:
        return "off"
    return f"{branch},STRICT" if value & _STRICT else branch


def ensure() -> str | None:
    """`mode()`, after setting `MKL_CBWR` (default `default_mode()`) where MKL started without a
    strict mode and has not multiplied anything yet. Warns when the mode is not strict: float32
    results on CPU then depend on the thread count."""
    current = mode()
    if current is not None and not current.endswith("STRICT"):
        wanted = os.environ.get("MKL_CBWR", default_mode()).upper().split(",")
        if wanted[0] in _CODES:
            strict = _STRICT if "STRICT" in wanted[1:] else 0
            _mkl().mkl_serv_cbwr_set(_CODES[wanted[0]] | strict)  # refused once MKL has run
            current = mode()
    if current is not None and not current.endswith("STRICT"):
        log.warning(
            "MKL runs without strict reproducibility (%s): float32 results on CPU depend on the "
            "thread count; start the process with MKL_CBWR=%s", current, default_mode()
        )  # fmt: skip
    return current


def numerics_follow_threads(device_type: str, dtype: str = "float32") -> bool:
    """Whether the thread count can change the bits of work on `device_type` ("cpu", "cuda")
    in `dtype`: on CPU unless it is float32 with MKL in a strict mode (`ensure`)."""
    if device_type != "cpu":
        return False
    current = ensure()
    return dtype != "float32" or current is None or not current.endswith("STRICT")
