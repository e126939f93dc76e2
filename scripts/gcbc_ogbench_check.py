"""Check our GCBC against OGBench's GCBC recipe: train variants on our segments, evaluate each
in OGBench's own gymnasium env with its own evaluation loop (`impls/utils/evaluation.py`: reset
with `task_id`, mean action at temperature 0, clip to [-1, 1], success from `info`, 1000 steps).

Variants (`--arch`):
- `ours`: `pipeline.model.policy.GaussianPolicy` (3 ReLU layers of `--hidden` on the mean path,
  inputs and actions normalized with the train stats) — what `oposm gcbc` fits.
- `ogb`: OGBench's `GCActor` as `impls/agents/gcbc.py` builds it: an MLP of `--layers` x
  `--hidden` GELU, raw (unnormalized) observation and goal, mean head initialized at scale 1e-2,
  constant std 1 in raw action units (loss: 0.5 * squared error).

Goals: OGBench's GCBC sampling (`pipeline.training.bc.hindsight_goals`, uniform over the future of
the same episode), or `--goals geom` (geometric, discount `--discount`).

Writes one JSON line per evaluation to `--out`. Usage (from the repository root):

    PYTHONPATH=$PWD python scripts/gcbc_ogbench_check.py --segments data/.../segments/<name> \
        --env pointmaze-medium-v0 --arch ogb --steps 5000 --eval-at 1000 5000 --out data/x.jsonl
"""

from __future__ import annotations

import argparse
import json
import math
import time

import gymnasium
import numpy as np
import ogbench.locomaze  # noqa: F401  (registers the envs)
import torch
from torch import nn

from pipeline.model.checkpoint import load_policy
from pipeline.model.policy import GaussianPolicy, PolicyConfig
from pipeline.segments import load_segments
from pipeline.training.bc import episode_ends, hindsight_goals
from pipeline.training.dynamics import transition_index


class OGBActor(nn.Module):
    """OGBench's `GCActor` (const std): MLP(hidden_dims, GELU, activate_final) + linear mean."""

    def __init__(self, in_dim: int, out_dim: int, hidden: int, layers: int):
        super().__init__()
        dims = [in_dim] + [hidden] * layers
        mods: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:], strict=True):
            mods += [nn.Linear(a, b), nn.GELU()]
        self.trunk = nn.Sequential(*mods)
        self.mean = nn.Linear(hidden, out_dim)
        for m in self.modules():  # flax default_init: variance_scaling(scale, fan_avg, uniform)
            if isinstance(m, nn.Linear):
                scale = 1e-2 if m is self.mean else 1.0
                limit = math.sqrt(3 * scale / ((m.in_features + m.out_features) / 2))
                nn.init.uniform_(m.weight, -limit, limit)
                nn.init.zeros_(m.bias)

    def forward(self, s: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        return self.mean(self.trunk(torch.cat([s, g], -1)))


def geom_goals(segments, steps: np.ndarray, rng: np.random.Generator, discount: float):
    last = episode_ends(segments, steps)
    return np.minimum(steps + rng.geometric(1 - discount, len(steps)), last)


def make_model(args, seg):
    sd, ad = seg.info.state_dim, seg.info.action_dim
    if args.arch == "ogb":
        return OGBActor(sd + 2, ad, args.hidden, args.layers)
    policy = GaussianPolicy(PolicyConfig(sd, ad, (0, 1), args.hidden, 1e-4, False))
    st = seg.stats
    if args.normalize:
        policy.set_normalization(
            {k: getattr(st, k) for k in ("state_mean", "state_std", "action_mean", "action_std")}
        )
    return policy


def mean_action(model, s: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    if isinstance(model, OGBActor):
        return model(s, g)
    return model.action_stats(s, g)[0]


def loss_fn(model, s, a, g) -> torch.Tensor:
    if isinstance(model, OGBActor):
        return 0.5 * (model(s, g) - a).square().sum(-1).mean()
    return model.nll(s, a, g).mean()


@torch.no_grad()
def evaluate(model, env_id: str, episodes: int, seed: int) -> dict:
    """OGBench's evaluation loop, run for all episodes of a task side by side."""
    np.random.seed(seed)  # OGBench's task noise comes from numpy's global generator
    envs = [gymnasium.make(env_id) for _ in range(episodes)]
    per_task = []
    for task in range(1, 6):
        obs, goals = [], []
        for e in envs:
            ob, info = e.reset(options={"task_id": task})
            obs.append(ob)
            goals.append(info["goal"])
        obs, goals = np.array(obs), np.array(goals)
        alive = np.ones(episodes, bool)
        success = np.zeros(episodes)
        while alive.any():
            idx = np.flatnonzero(alive)
            s = torch.as_tensor(obs[idx], dtype=torch.float32)
            g = torch.as_tensor(goals[idx], dtype=torch.float32)
            act = np.clip(mean_action(model, s, g).double().numpy(), -1, 1)
            for k, i in enumerate(idx):
                ob, _, term, trunc, info = envs[i].step(act[k])
                obs[i] = ob
                if term or trunc:
                    alive[i] = False
                    success[i] = info["success"]
        per_task.append(float(success.mean()))
    return {"tasks": per_task, "overall": float(np.mean(per_task))}


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--segments")
    p.add_argument("--env", required=True)
    p.add_argument("--arch", choices=["ours", "ogb"], default="ours")
    p.add_argument("--hidden", type=int, default=128)
    p.add_argument("--layers", type=int, default=3)
    p.add_argument("--normalize", type=int, default=1)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--steps", type=int, default=5000)
    p.add_argument("--eval-at", type=int, nargs="+", default=[])
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--goals", choices=["uniform", "geom"], default="uniform")
    p.add_argument("--discount", type=float, default=0.99)
    p.add_argument("--train-episodes", type=int, default=0, help="0: all of the train split")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out")
    p.add_argument("--tag", default="")
    p.add_argument("--checkpoint", help="only evaluate this `oposm gcbc` model folder")
    args = p.parse_args()
    torch.set_num_threads(1)
    if args.checkpoint:
        policy, _ = load_policy(args.checkpoint, "gcbc")
        res = evaluate(policy, args.env, args.episodes, args.seed)
        print(json.dumps({"tag": args.tag, "checkpoint": args.checkpoint, **res}), flush=True)
        return
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    seg = load_segments(args.segments)
    train_idx = transition_index(seg, "train")
    if args.train_episodes:
        keep = seg.episodes_in("train")[: args.train_episodes]
        off = seg.episode_offsets
        train_idx = np.concatenate([np.arange(off[e], off[e + 1] - 1) for e in keep])
    states = torch.as_tensor(seg.states)
    actions = torch.as_tensor(seg.actions)
    val_idx = transition_index(seg, "validation")
    vrng = np.random.default_rng([args.seed, 1])
    val_idx = np.sort(vrng.choice(val_idx, min(5000, val_idx.size), replace=False))
    val_g = hindsight_goals(seg, val_idx, vrng)
    model = make_model(args, seg)
    opt = torch.optim.Adam([q for q in model.parameters() if q.requires_grad], lr=args.lr)
    eval_at = set(args.eval_at) | {args.steps}
    t0, losses = time.monotonic(), []
    for step in range(1, args.steps + 1):
        idx = train_idx[rng.integers(train_idx.size, size=args.batch)]
        if args.goals == "uniform":
            gidx = hindsight_goals(seg, idx, rng)
        else:
            gidx = geom_goals(seg, idx, rng, args.discount)
        loss = loss_fn(model, states[idx], actions[idx], states[gidx][:, :2])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(loss.item())
        if step in eval_at:
            model.eval()
            train_s = time.monotonic() - t0
            with torch.no_grad():
                vs, va, vg = states[val_idx], actions[val_idx], states[val_g][:, :2]
                val_mse = float((mean_action(model, vs, vg) - va).square().sum(-1).mean())
            res = evaluate(model, args.env, args.episodes, args.seed)
            model.train()
            row = {
                "tag": args.tag,
                "step": step,
                **{k: v for k, v in vars(args).items() if k not in ("out", "eval_at", "tag")},
                "loss": float(np.mean(losses[-200:])),
                "val_mse": val_mse,
                "train_s": round(train_s, 1),
                "eval_s": round(time.monotonic() - t0 - train_s, 1),
                **res,
            }
            print(json.dumps(row), flush=True)
            with open(args.out, "a") as f:
                f.write(json.dumps(row) + "\n")
            t0 = time.monotonic() - train_s


if __name__ == "__main__":
    main()
