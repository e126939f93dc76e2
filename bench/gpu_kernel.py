"""The fused rollout kernel alone (`pipeline/planning/triton_rollout.py`) against what it replaces,
the torch rollout plus `GoalCost` (`SkillPlanner._rollout`), at table 14's candidate shapes (L 10,
K 100) for 1 and 256 problems: one CEM iteration's model work.

Each is timed as GPU time per call from a replayed CUDA graph (so launch overhead is left out on
both sides: what a captured plan pays), median of `--repeats` replays of 20 calls each. The
kernel's launch settings are compared: float32 IEEE products (the default: the eager planner's
numbers), TF32 tensor-core products, bfloat16 weights; 4 or 8 warps. Models: the trained default
model when `data/models/pointmaze-medium` exists (else random weights of its size), and random
weights at the paper's size (h = z = 256) and the ant's (state 29, z 64, h 256). Every variant's
largest cost difference from the torch float32 cost is printed beside its time.

    python bench/gpu_kernel.py [--out kernel.json]        (one CUDA GPU; ~1 min)
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections.abc import Callable
from pathlib import Path

import torch

from pipeline.config import PlannerParams, TrainParams
from pipeline.model import SkillModel
from pipeline.model.checkpoint import load_model
from pipeline.model.settings import skill_model_config
from pipeline.planning import GoalCost, SkillPlanner
from pipeline.planning.fused import PlannerNets
from pipeline.planning.settings import planner_config
from pipeline.planning.triton_rollout import TritonNets

VARIANTS = {  # label: (weights dtype, precision, warps)
    "ieee_w4": (torch.float32, "ieee", 4),
    "ieee_w8": (torch.float32, "ieee", 8),
    "tf32_w4": (torch.float32, "tf32", 4),
    "bf16_w4": (torch.bfloat16, "", 4),
    "bf16_w8": (torch.bfloat16, "", 8),
}


def graph_ms(call: Callable[[], object], repeats: int, per_graph: int = 20) -> float:
    """Median GPU milliseconds per call, `per_graph` calls captured in one graph."""
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(3):
            call()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        for _ in range(per_graph):
            call()
    times = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        graph.replay()
        end.record()
        end.synchronize()
        times.append(start.elapsed_time(end) / per_graph)
    return statistics.median(times)


def _models(data: Path, device: str) -> dict[str, SkillModel]:
    trained = data / "models/pointmaze-medium"
    if trained.exists():
        default, _ = load_model(trained, device=device)
    else:
        default = SkillModel(skill_model_config(TrainParams(), 4, 2)).to(device)
    torch.manual_seed(0)
    paper = SkillModel(skill_model_config(TrainParams(z_dim=256, hidden=256), 4, 2)).to(device)
    ant = SkillModel(skill_model_config(TrainParams(z_dim=64, hidden=256), 29, 8)).to(device)
    return {"default": default, "paper": paper, "ant": ant}


def _bench_shape(
    model: SkillModel, problems: int, variants: dict, repeats: int, key: str, device: str
) -> dict[str, float]:
    """The torch rollout + cost and each kernel variant on `problems` x 100 candidates."""
    planner = SkillPlanner(model, planner_config(PlannerParams()))  # its rollout only
    sd, z = model.config.state_dim, model.config.z_dim
    g = torch.Generator().manual_seed(problems)
    eps = torch.randn(problems, 100, 10, z, generator=g).to(device)
    s0 = (torch.randn(problems, sd, generator=g) * 0.1).to(device)
    goals = torch.randn(problems, 2, generator=g).to(device)
    nets = PlannerNets(model)
    s0_n = model.norm_states(s0)
    prior0 = nets.prior(s0_n)
    cost = GoalCost(goals)

    def torch_call() -> torch.Tensor:
        return cost(planner._rollout(eps, nets, s0, s0_n, prior0)[0])

    want = torch_call()
    out = {f"{key}_torch_ms": graph_ms(torch_call, repeats)}
    for label, (dtype, precision, warps) in variants.items():
        fused = TritonNets(model, dtype)
        fused.precision, fused.num_warps = precision, warps

        goal = fused.goal_inputs(goals, (0, 1))

        def call(fused: TritonNets = fused, goal: tuple = goal) -> torch.Tensor:
            return fused.rollout_cost(eps, s0, s0_n, prior0, goal, 0.0)[2]

        out[f"{key}_{label}_max_cost_diff"] = float((call() - want).abs().max())
        ms = graph_ms(call, repeats)
        out[f"{key}_{label}_ms"] = ms
        out[f"{key}_{label}_speedup"] = out[f"{key}_torch_ms"] / ms
    return out


@torch.no_grad()
def bench_kernel(data: Path, repeats: int, device: str = "cuda") -> dict[str, float]:
    out: dict[str, float] = {}
    for name, model in _models(data, device).items():
        model.eval()
        variants = (
            VARIANTS if name == "default" else {k: VARIANTS[k] for k in ("ieee_w4", "bf16_w4")}
        )
        for problems in (1, 256):
            got = _bench_shape(model, problems, variants, repeats, f"{name}_{problems}p", device)
            print({k: round(v, 4) for k, v in got.items()}, flush=True)
            out |= got
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data", type=Path, default=Path("data"))
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    numbers = bench_kernel(args.data, args.repeats)
    if args.out:
        args.out.write_text(json.dumps(numbers, indent=1))
    width = max(map(len, numbers))
    for key, value in numbers.items():
        print(f"{key:{width}s} {value:12.5f}")


if __name__ == "__main__":
    main()
