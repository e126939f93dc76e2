"""One table of the GPU checks (`bench/gpu.sh`): planning and training benchmarks on CUDA, each
against its reference or roofline measured in the same process, and the issue-16 targets."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from bench.plan import bench_plan
from bench.train import bench_train
from pipeline.config import load_params
from pipeline.paths import Paths

TARGETS = {  # issue 16, measured on one GPU
    "oposm_table14_compiled_replan_1env_p50_s": ("<=", 0.005),
    "oposm_table14_compiled_plans_per_s_256envs": (">=", 2000.0),
    "train_paper_windows_per_s": (">=", 50_000.0),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data", type=Path, default=Path("data"))
    parser.add_argument("--out", type=Path, default=None, help="Also write the numbers as JSON.")
    parser.add_argument("--train-steps", type=int, default=200)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, stream=sys.stderr)
    numbers: dict[str, float] = {}
    plan = load_params(Path("params.yaml"), ["deploy.device=cuda"])
    for envs in (64, 256):  # one-env numbers: the second run's
        numbers |= bench_plan(plan, Paths(args.data), envs, repeats=10, batch_repeats=3,
                              compiled=True, reference_envs=8)  # fmt: skip
    for label, params in (("default", "params.yaml"), ("paper", "params-paper.yaml")):
        p = load_params(Path(params), ["train.device=cuda"])
        got = bench_train(p, Paths(args.data), args.train_steps)
        numbers |= {f"train_{label}_{k}": v for k, v in got.items()}
    width = max(map(len, numbers))
    print(f"{'number':{width}s} {'value':>16s}  target")
    for name, value in numbers.items():
        check = ""
        if name in TARGETS:
            op, bound = TARGETS[name]
            ok = value <= bound if op == "<=" else value >= bound
            check = f"{op} {bound:g}: {'met' if ok else 'NOT met'}"
        print(f"{name:{width}s} {value:16,.4f}  {check}")
    if args.out:
        args.out.write_text(json.dumps(numbers, indent=1))


if __name__ == "__main__":
    main()
