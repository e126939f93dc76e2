"""The machine's matrix-multiply throughput, measured: the roofline the benchmarks' achieved
GFLOP/s are set against, in the precision the benchmarked code multiplies in (float32 unless
`train.dtype` says bfloat16)."""

from __future__ import annotations

import time

import torch


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def matmul_gflops(
    device: torch.device,
    m: int,
    k: int,
    n: int,
    seconds: float = 0.5,
    dtype: torch.dtype = torch.float32,
) -> float:
    """Measured GFLOP/s of `[m, k] @ [k, n]` products in `dtype` on `device` (after a warm-up)."""
    a = torch.randn(m, k, device=device, dtype=dtype)
    b = torch.randn(k, n, device=device, dtype=dtype)
    for _ in range(3):
        a @ b
    _sync(device)
    flops, repeats, elapsed = 2.0 * m * k * n, 0, 0.0
    start = time.perf_counter()
    while elapsed < seconds:
        for _ in range(max(1, int(1e8 / flops))):
            a @ b
            repeats += 1
        _sync(device)
        elapsed = time.perf_counter() - start
    return flops * repeats / elapsed / 1e9


def roofline(
    device: torch.device, hidden: int, dtype: torch.dtype = torch.float32
) -> dict[str, float]:
    """The best of a large square product and of planner-shaped ones (`[rows, h] @ [h, h]`), in
    `dtype`."""
    big = 4096 if device.type == "cuda" else 1024
    shapes = {"square": (big, big, big), "layer": (6400, hidden, hidden)}
    out = {
        f"matmul_{name}_gflops": matmul_gflops(device, *shape, dtype=dtype)
        for name, shape in shapes.items()
    }
    out["roofline_gflops"] = max(out.values())
    return out
