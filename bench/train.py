"""Training benchmark (`oposm bench train`): EM (or VI) steps/s and sub-trajectories/s."""

from __future__ import annotations

import logging
import time

import torch

from pipeline.config import Params
from pipeline.devices import resolve_device
from pipeline.model import SkillModel, SkillModelConfig
from pipeline.paths import Paths
from pipeline.segments import load_segments
from pipeline.training.data import WindowSampler
from pipeline.training.updaters import make_updater

log = logging.getLogger(__name__)


def bench_train(params: Params, paths: Paths, steps: int, warmup: int = 5) -> dict[str, float]:
    """Time `steps` update steps (after `warmup`) of `train.method` at the train params' model
    size, on the segments of `ingest.name` (`oposm segment`)."""
    cfg = params.train
    device = resolve_device(cfg.device, "train.device")
    segments = load_segments(paths.segments(params.ingest.name))
    log.info(
        "timing %d %s steps (after %d warm-up) on %s: z %d, hidden %d, batch %d",
        steps,
        cfg.method,
        warmup,
        device,
        cfg.z_dim,
        cfg.hidden,
        cfg.batch_size,
    )
    torch.manual_seed(cfg.seed)
    config = SkillModelConfig(
        segments.info.state_dim,
        segments.info.action_dim,
        cfg.z_dim,
        cfg.hidden,
        cfg.tawm_shared_std,
        cfg.min_std,
    )
    model = SkillModel(config).to(device)
    updater = make_updater(cfg.method, model, cfg.lr_e, cfg.lr_m, cfg.grad_clip)
    sampler = WindowSampler(segments, "train", device, cfg.seed)
    for _ in range(warmup):
        updater.step(sampler.sample(cfg.batch_size))
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(steps):
        updater.step(sampler.sample(cfg.batch_size))
    if device.type == "cuda":
        torch.cuda.synchronize()
    elapsed = time.perf_counter() - start
    return {
        "steps_per_s": steps / elapsed,
        "windows_per_s": steps * cfg.batch_size / elapsed,
        "ms_per_step": 1000 * elapsed / steps,
        "parameters": float(sum(p.numel() for p in model.parameters())),
        "threads": float(torch.get_num_threads()),
    }
