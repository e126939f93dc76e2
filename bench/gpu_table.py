"""One table of the GPU checks (`bench/gpu.sh`): planning and training benchmarks on CUDA, each
against its reference or roofline measured in the same process, and the issue-16 targets.

Each section runs on its own: one that fails logs its error and the others still report. The
numbers are written to `--out` after every section, so a run cut off at its time limit keeps
what it measured. `--device cpu --envs 4 --no-compile --train-steps 3` is a quick dry run of
the plumbing on a machine without a GPU."""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import torch

from bench.plan import bench_plan
from bench.train import bench_train
from pipeline.config import load_params
from pipeline.paths import Paths

log = logging.getLogger("bench.gpu_table")

TARGETS = {  # issue 16, measured on one GPU
    "oposm_table14_compiled_replan_1env_p50_s": ("<=", 0.005),
    "oposm_table14_compiled_plans_per_s_256envs": (">=", 2000.0),
    "oposm_table14_triton_compiled_replan_1env_p50_s": ("<=", 0.005),
    "oposm_table14_triton_compiled_plans_per_s_256envs": (">=", 2000.0),
    "bf16_oposm_table14_triton_compiled_replan_1env_p50_s": ("<=", 0.005),
    "bf16_oposm_table14_triton_compiled_plans_per_s_256envs": (">=", 2000.0),
    "train_paper_compiled_windows_per_s": (">=", 50_000.0),
    "train_paper_windows_per_s": (">=", 50_000.0),
    "train_paper_graph_windows_per_s": (">=", 50_000.0),
    "train_paper_compiled_graph_windows_per_s": (">=", 50_000.0),
    "train_paper_graph_bf16_windows_per_s": (">=", 50_000.0),
}


def _sections(args: argparse.Namespace) -> dict[str, Callable[[], dict[str, float]]]:
    """name -> a call returning numbers; training first (quick, no planner compile)."""
    data, device = Paths(args.data), args.device

    def train(
        params: str,
        label: str,
        compile: bool,
        graph: bool = False,
        batch: int | None = None,
        dtype: str = "float32",
    ) -> Callable[[], dict[str, float]]:
        def run() -> dict[str, float]:
            over = [f"train.device={device}", f"train.compile={str(compile).lower()}"]
            over += [f"train.cuda_graph={str(graph).lower()}", f"train.dtype={dtype}"]
            over += [f"train.batch_size={batch}"] if batch else []
            got = bench_train(load_params(Path(params), over), data, args.train_steps)
            return {f"train_{label}_{k}": v for k, v in got.items()}

        return run

    def plan(envs: int, dtype: str = "float32") -> Callable[[], dict[str, float]]:
        def run() -> dict[str, float]:
            over = [f"deploy.device={device}", f"deploy.planner.dtype={dtype}"]
            params = load_params(Path("params.yaml"), over)
            got = bench_plan(params, data, envs, repeats=10, batch_repeats=3,
                             compiled=args.compile, reference_envs=8, triton=args.triton,
                             reference=dtype == "float32")  # fmt: skip
            prefix = "" if dtype == "float32" else "bf16_"  # the reference: float32's section
            return {prefix + k: v for k, v in got.items()}

        return run

    sections = {
        "train_default": train("params.yaml", "default", False),
        "train_paper": train("params-paper.yaml", "paper", False),
    }
    sections["train_paper_graph"] = train("params-paper.yaml", "paper_graph", False, True)
    sections["train_paper_graph_b1000"] = train(
        "params-paper.yaml", "paper_graph_b1000", False, True, 1000
    )
    sections["train_default_graph"] = train("params.yaml", "default_graph", False, True)
    sections["train_paper_graph_bf16"] = train(  # train.dtype bfloat16 (autocast)
        "params-paper.yaml", "paper_graph_bf16", False, True, dtype="bfloat16"
    )
    if args.compile:
        sections["train_paper_compiled"] = train("params-paper.yaml", "paper_compiled", True)
        sections["train_paper_compiled_graph"] = train(
            "params-paper.yaml", "paper_compiled_graph", True, True
        )
    for envs in args.envs:  # the one-environment numbers: the last section's (first: targets)
        sections[f"plan_{envs}envs"] = plan(envs)
    for envs in args.bf16_envs:
        sections[f"plan_{envs}envs_bf16"] = plan(envs, "bfloat16")
    if args.only:
        sections = {k: v for k, v in sections.items() if re.search(args.only, k)}
    return sections


def print_table(numbers: dict[str, float], failed: list[str]) -> None:
    width = max(map(len, numbers), default=10)
    print(f"{'number':{width}s} {'value':>16s}  target")
    for name, value in numbers.items():
        check = ""
        if name in TARGETS:
            op, bound = TARGETS[name]
            ok = value <= bound if op == "<=" else value >= bound
            check = f"{op} {bound:g}: {'met' if ok else 'NOT met'}"
        print(f"{name:{width}s} {value:16,.4f}  {check}")
    for name in failed:
        print(f"{name}: FAILED (traceback in the log)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data", type=Path, default=Path("data"))
    parser.add_argument("--out", type=Path, default=None, help="Also write the numbers as JSON.")
    parser.add_argument("--train-steps", type=int, default=300)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--envs", type=int, nargs="*", default=[256, 64])
    parser.add_argument("--no-compile", dest="compile", action="store_false")
    parser.add_argument(
        "--no-triton",
        dest="triton",
        action="store_false",
        help="Leave out the planners on the fused Triton kernel.",
    )
    parser.add_argument(
        "--bf16-envs",
        type=int,
        nargs="*",
        default=[],
        help="Also plan in bfloat16 at these batch sizes (no reference).",
    )
    parser.add_argument("--only", default="", help="Run only the sections this regex finds.")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, stream=sys.stderr)
    # Every bench_plan call builds new compiled planners (each a cache entry of the same code).
    torch._dynamo.config.recompile_limit = 64
    numbers: dict[str, float] = {}
    failed: list[str] = []
    for name, section in _sections(args).items():
        start = time.perf_counter()
        log.info("== %s", name)
        try:
            numbers |= section()
        except Exception:  # report the rest; this one's traceback goes to the log
            failed.append(name)
            traceback.print_exc()
        numbers[f"seconds_{name}"] = time.perf_counter() - start
        if args.out:
            args.out.write_text(json.dumps(numbers | {"failed": failed}, indent=1))
    print_table(numbers, failed)
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
