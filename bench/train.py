"""Training benchmark (`oposm bench train`): EM (or VI) steps/s, sub-trajectories (windows)/s,
FLOPs per step (the matrix products of forward and backward passes, counted by torch) and the
achieved GFLOP/s against a matrix-multiply measurement of the same device in `train.dtype`
(`bench/roofline.py`); beside them THE REFERENCE, the paper's EM step as its code runs it
(`bench/reference_em.py`), timed the same way at the same sizes on the same windows
(`reference/*`, and `speedup_over_reference`)."""

from __future__ import annotations

import logging
import os
import time

import torch
from torch.utils.flop_counter import FlopCounterMode

from bench.reference_em import ReferenceEM
from bench.roofline import roofline
from pipeline.config import Params
from pipeline.devices import auto_threads, resolve_device, torch_threads
from pipeline.model import SkillModel
from pipeline.paths import Paths
from pipeline.segments import load_segments
from pipeline.training.cuda_graphs import CudaGraphUpdater
from pipeline.training.data import WindowSampler
from pipeline.training.updaters import updater_for
from stages.train import model_config

log = logging.getLogger(__name__)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def bench_train(
    params: Params, paths: Paths, steps: int, warmup: int = 5, reference: bool = True
) -> dict[str, float]:
    """Time `steps` update steps (after `warmup`) of `train.method` at the train params' model
    size, on the segments of `ingest.name` (`oposm segment`), on `train.threads` CPU threads;
    with `reference`, then the paper's procedure (`reference_em.ReferenceEM`) likewise."""
    cfg = params.train
    device = resolve_device(cfg.device, "train.device")
    segments = load_segments(paths.segments(params.ingest.name))
    with torch_threads(auto_threads(cfg.threads) if device.type == "cpu" else None):
        log.info(
            "timing %d %s steps (after %d warm-up) on %s: z %d, hidden %d, batch %d, %s "
            "encoder, %s%s",
            steps, cfg.method, warmup, device, cfg.z_dim, cfg.hidden, cfg.batch_size,
            cfg.encoder, cfg.dtype,
            ", CUDA graphs" if cfg.cuda_graph and device.type == "cuda" else "",
        )  # fmt: skip
        out: dict[str, float] = {"load_1min_before": os.getloadavg()[0]}
        torch.manual_seed(cfg.seed)
        model = SkillModel(model_config(cfg, segments)).to(device)
        updater = updater_for(cfg, model)
        sampler = WindowSampler(segments, "train", device, cfg.seed, chain=cfg.tawm_chain)
        with FlopCounterMode(display=False) as counter:  # eager: a graph replay is not seen
            updater.step(sampler.sample(cfg.batch_size))
        if cfg.cuda_graph and device.type == "cuda":
            updater = CudaGraphUpdater(updater)
        for _ in range(warmup):  # with cuda_graph: the capture
            updater.step(sampler.sample(cfg.batch_size))
        _sync(device)
        start = time.perf_counter()
        for _ in range(steps):
            updater.step(sampler.sample(cfg.batch_size))
        _sync(device)
        elapsed = time.perf_counter() - start
        flops = float(counter.get_total_flops())
        out |= {
            "steps_per_s": steps / elapsed,
            "windows_per_s": steps * cfg.batch_size / elapsed,
            "ms_per_step": 1000 * elapsed / steps,
            "flops_per_step": flops,
            "gflops": flops * steps / elapsed / 1e9,
            "parameters": float(sum(p.numel() for p in model.parameters())),
            "threads": float(torch.get_num_threads()),
            "load_1min_after": os.getloadavg()[0],
        }
        out |= roofline(device, cfg.hidden, getattr(torch, cfg.dtype))  # in train.dtype
        out["roofline_fraction"] = out["gflops"] / out["roofline_gflops"]
        if reference:
            ref = _time_reference(params, sampler, segments, device, steps, warmup)
            ref["roofline_fraction"] = ref["gflops"] / out["roofline_gflops"]
            out |= {f"reference/{k}": v for k, v in ref.items()}
            out["speedup_over_reference"] = out["steps_per_s"] / ref["steps_per_s"]
    return out


def _time_reference(
    params: Params, sampler: WindowSampler, segments, device: torch.device, steps: int, warmup: int
) -> dict[str, float]:
    """The paper's EM step (`ReferenceEM`) at the train params' sizes and `train.dtype`, timed
    as `bench_train` times the pipeline's."""
    cfg = params.train
    torch.manual_seed(cfg.seed)
    info = segments.info
    ref = ReferenceEM(info.state_dim, info.action_dim, cfg.z_dim, cfg.hidden, cfg.lr_m).to(device)
    dtype = getattr(torch, cfg.dtype)
    with FlopCounterMode(display=False) as counter:
        ref.step(sampler.sample(cfg.batch_size), dtype)
    for _ in range(warmup):
        ref.step(sampler.sample(cfg.batch_size), dtype)
    _sync(device)
    start = time.perf_counter()
    for _ in range(steps):
        ref.step(sampler.sample(cfg.batch_size), dtype)
    _sync(device)
    elapsed = time.perf_counter() - start
    flops = float(counter.get_total_flops())
    return {
        "steps_per_s": steps / elapsed,
        "flops_per_step": flops,
        "gflops": flops * steps / elapsed / 1e9,
        "parameters": float(sum(p.numel() for p in ref.parameters())),
    }


def bench_train_dtypes(
    params: Params, paths: Paths, steps: int, dtypes: list[str], reference: bool = True
) -> dict[str, float]:
    """`bench_train` once per `train.dtype` in `dtypes`, in this process one after the other;
    each number prefixed with its dtype, and each dtype's steps/s over the first's."""
    out: dict[str, float] = {}
    for dtype in dtypes:
        train = params.train.model_copy(update={"dtype": dtype})
        got = bench_train(params.model_copy(update={"train": train}), paths, steps,
                          reference=reference)  # fmt: skip
        out |= {f"{dtype}/{k}": v for k, v in got.items()}
    for dtype in dtypes[1:]:
        ratio = out[f"{dtype}/steps_per_s"] / out[f"{dtypes[0]}/steps_per_s"]
        out[f"{dtype}_over_{dtypes[0]}"] = ratio
    return out
