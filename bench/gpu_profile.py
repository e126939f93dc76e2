"""Where the GPU time goes (`python bench/gpu_profile.py`, after `bench/gpu.sh`): for one plan
of the default and the table-14 planner (compiled CEM iterations, not graphed, so the profiler
sees each kernel) and for one EM step at the paper's sizes (eager and `train.compile`), the CUDA
kernels launched, their summed run time and the wall time. Kernels per CEM iteration and the
fraction of wall time the GPU is busy say whether a faster plan needs fewer kernels (fusion) or
faster ones. Also the largest gap between CUDA's and the CPU's training gradients (cuDNN's GRU,
with and without TF32), which `tests/test_gpu.py` bounds.

Also runs on CPU (`--device cpu --no-compile`: a quick dry run), where kernels are CPU ops."""

from __future__ import annotations

import argparse
import copy
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

from pipeline.config import PlannerParams, TrainParams, load_params
from pipeline.model import SkillModel
from pipeline.model.checkpoint import load_model
from pipeline.model.settings import skill_model_config
from pipeline.paths import Paths
from pipeline.planning import GoalCost, SkillPlanner, problem_keys
from pipeline.planning.settings import planner_config
from pipeline.segments import load_segments
from pipeline.training.data import WindowBatch, WindowSampler
from pipeline.training.losses import e_objective, m_objective, vi_objective
from pipeline.training.updaters import updater_for


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def kernel_profile(call: Callable[[], object], device: torch.device) -> dict[str, float]:
    """Kernels (CUDA kernels, or CPU ops on CPU), their summed time and the wall time of `call`."""
    call()  # warm-up: compilation, allocator
    _sync(device)
    activity = ProfilerActivity.CUDA if device.type == "cuda" else ProfilerActivity.CPU
    start = time.perf_counter()
    with profile(activities=[activity]) as prof:
        call()
        _sync(device)
    wall = time.perf_counter() - start
    start = time.perf_counter()
    call()
    _sync(device)
    unprofiled = time.perf_counter() - start
    if device.type == "cuda":
        kernels = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
        busy = sum(e.device_time for e in kernels) / 1e6
    else:
        kernels = [e for e in prof.events() if e.cpu_parent is None]
        busy = sum(e.cpu_time_total for e in kernels) / 1e6
    return {"kernels": float(len(kernels)), "kernel_s": busy, "wall_s": unprofiled,
            "profiled_wall_s": wall}  # fmt: skip


def profile_plans(params, paths: Paths, device: torch.device, compile: bool) -> dict[str, float]:
    model, _ = load_model(paths.existing(paths.model(params.ingest.name)), device=device)
    segments = load_segments(paths.existing(paths.segments(params.ingest.name)))
    s0 = torch.as_tensor(segments.states[:1], dtype=torch.float32, device=device)
    goals = s0[:, :2] + 1.0
    out = {}
    default = PlannerParams(prior_weight=0.0, compile=compile)  # the CEM sizes; the paper's cost
    table14 = default.model_copy(update={"elites": 50, "iterations": 100})
    for label, config in (
        ("default", planner_config(default)),
        ("table14", planner_config(table14)),
    ):
        planner = SkillPlanner(model, config)
        keys = problem_keys([0], device)

        def search(planner=planner, keys=keys) -> object:  # compiled iterations, no graph
            return planner._search(s0, GoalCost(goals), keys, planner.initial_mean(1))

        got = kernel_profile(search, device)
        iterations = config.cem.iterations
        out |= {f"plan_{label}_1env_{k}": v for k, v in got.items()}
        out[f"plan_{label}_kernels_per_iteration"] = got["kernels"] / iterations
        out[f"plan_{label}_gpu_busy_fraction"] = got["kernel_s"] / got["wall_s"]
        out[f"plan_{label}_us_per_kernel_wall"] = 1e6 * got["wall_s"] / max(got["kernels"], 1)
    return out


def profile_train(params, paths: Paths, device: torch.device, compile: bool) -> dict[str, float]:
    cfg = params.train
    segments = load_segments(paths.existing(paths.segments(params.ingest.name)))
    sampler = WindowSampler(segments, "train", device, 0)
    batch = sampler.sample(cfg.batch_size)
    out = {}
    for compiled in (False, True) if compile else (False,):
        torch.manual_seed(0)
        config = skill_model_config(cfg, segments.info.state_dim, segments.info.action_dim)
        model = SkillModel(config).to(device)
        updater = updater_for(cfg.model_copy(update={"compile": compiled}), model)
        got = kernel_profile(lambda updater=updater: updater.step(batch), device)
        label = "compiled" if compiled else "eager"
        out |= {f"train_paper_{label}_step_{k}": v for k, v in got.items()}
        out[f"train_paper_{label}_gpu_busy_fraction"] = got["kernel_s"] / got["wall_s"]
    return out


def gradient_gap(device: torch.device) -> dict[str, float]:
    """Largest absolute and relative gaps of the objectives' gradients, device vs CPU, with
    cuDNN's TF32 on (torch's default) and off."""
    torch.manual_seed(0)
    cpu = SkillModel(skill_model_config(TrainParams(z_dim=8, hidden=64), 4, 2))
    cpu.set_normalization([0.5, -0.5, 0.0, 0.0], [2.0, 2.0, 1.0, 1.0], [0.0, 0.0], [0.5, 0.5])
    g = torch.Generator().manual_seed(1)
    batch = WindowBatch(torch.randn(32, 11, 4, generator=g), torch.randn(32, 10, 2, generator=g))
    z = torch.randn(32, 8, generator=g)

    def grads(model: SkillModel, b: WindowBatch, z: torch.Tensor) -> list[torch.Tensor]:
        q = model.posterior_dist(b.states[:, :-1], b.actions)
        loss = e_objective(model, b, q, z) + m_objective(model, b, z)[0]
        loss = loss + vi_objective(model, b, q, z)[0]
        return [x.cpu() for x in torch.autograd.grad(loss, list(model.parameters()))]

    want = grads(cpu, batch, z)
    names = [n for n, _ in cpu.named_parameters()]
    out = {}
    previous = torch.backends.cudnn.allow_tf32
    for tf32 in (True, False):
        torch.backends.cudnn.allow_tf32 = tf32
        dev = copy.deepcopy(cpu).to(device)
        on = WindowBatch(batch.states.to(device), batch.actions.to(device))
        got = grads(dev, on, z.to(device))
        gaps = [(float((a - b).abs().max()), float(((a - b).abs() / (b.abs() + 1e-6)).max()), n)
                for a, b, n in zip(got, want, names, strict=True)]  # fmt: skip
        worst = max(gaps)
        tag = "tf32" if tf32 else "no_tf32"
        out[f"grad_gap_{tag}_max_abs"] = worst[0]
        out[f"grad_gap_{tag}_max_rel"] = max(gap[1] for gap in gaps)
        print(f"gradient gap ({tag}): worst {worst[2]} abs {worst[0]:.2e}")
    torch.backends.cudnn.allow_tf32 = previous
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data", type=Path, default=Path("data"))
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--no-compile", dest="compile", action="store_false")
    args = parser.parse_args()
    device = torch.device(args.device)
    paths = Paths(args.data)
    paper, default = load_params(Path("params-paper.yaml")), load_params(Path("params.yaml"))
    for section in (
        lambda: gradient_gap(device),
        lambda: profile_train(paper, paths, device, args.compile),
        lambda: profile_plans(default, paths, device, args.compile),
    ):
        for name, value in section().items():  # printed as each section ends
            print(f"{name:48s} {value:16,.6g}", flush=True)


if __name__ == "__main__":
    main()
