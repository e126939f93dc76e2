"""Replay an `oposm train` run step by step and record what feeds each EM update.

The replay builds the model, updater and samplers exactly as `stages.train` does (same seeds, same
draws), so its trajectory is the run's own: every `--every` steps, before the update, it computes
on the very batch the update will use (global RNG saved and restored, so the update draws the same
skills) the gradient norm of each term of eq. 15 with respect to the posterior (phi) and of each
term of eq. 16 with respect to its own network, and the log-stds of posterior, prior, policy and
TAWM. The validation s_T NLL with prior skills is computed every `--val-every` steps on the run's
validation windows (no random draws), so the rows can be checked against the run's dvclive log.

    uv run python scripts/em_trace.py -S train.seed=2 -S train.dtype=bfloat16 --steps 1000 \
        --out data/runs/em-trace-s2.csv
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path

import torch

from pipeline.config import load_params
from pipeline.model import SkillModel
from pipeline.model.skill_model import BOUND_TOLERANCE, censored_log_prob
from pipeline.paths import Paths
from pipeline.segments import load_segments
from pipeline.training.data import WindowSampler
from pipeline.training.loop import evaluate
from pipeline.training.losses import policy_log_prob
from pipeline.training.updaters import in_precision, updater_for
from stages.results_common import code_version
from stages.train import model_config


def _norm(grads) -> float:
    return math.sqrt(sum(float(g.pow(2).sum()) for g in grads if g is not None))


def _grad_norm(loss: torch.Tensor, params: list[torch.nn.Parameter]) -> float:
    return _norm(torch.autograd.grad(loss, params, retain_graph=True, allow_unused=True))


def action_terms(model: SkillModel, mean, std, a_n, low_n, high_n):
    """Per-element log pi `[B, T, ad]` (as the model scores it) and the mask of clipped ones."""
    at_bound = (a_n >= high_n - BOUND_TOLERANCE) | (a_n <= low_n + BOUND_TOLERANCE)
    if model.config.censored:
        per_dim = censored_log_prob(mean, std, a_n, low_n, high_n)
    else:
        per_dim = torch.distributions.Normal(mean, std).log_prob(a_n)
    return per_dim, at_bound


def diagnose(model: SkillModel, batch, dtype: str, low_n, high_n) -> dict[str, float]:
    """Per-term gradient norms and log-stds on `batch` (draws one z ~ q from the global RNG);
    `low_n`, `high_n`: the data's action bounds in normalized units."""

    def terms(model: SkillModel, batch):
        s0 = batch.states[:, 0]
        mu_q, std_q = model.posterior(batch.states[:, :-1], batch.actions)
        z = mu_q + std_q * torch.randn_like(std_q)
        mu_p, std_p = model.prior(s0)
        q = torch.distributions.Normal(mu_q, std_q)
        p = torch.distributions.Normal(mu_p, std_p)
        s = batch.states[:, :-1]
        mu_pi, std_pi = model.policy(torch.cat([s, z[:, None].expand(-1, s.shape[1], -1)], -1))
        mu_w, std_w = model.tawm(torch.cat([s0, z.detach()], -1))
        return dict(
            mu_q=mu_q, std_q=std_q, z=z, mu_p=mu_p, std_p=std_p, std_pi=std_pi, std_w=std_w,
            e_pi=-policy_log_prob(model, batch, z).mean(),
            e_prior=-p.log_prob(z).sum(-1).mean(),
            e_q=q.log_prob(z).sum(-1).mean(),
            m_pi=-policy_log_prob(model, batch, z.detach()).mean(),
            m_tawm=-torch.distributions.Normal(mu_w, std_w).log_prob(batch.states[:, -1])
            .sum(-1).mean(),
            m_prior=-torch.distributions.Normal(mu_p, std_p).log_prob(z.detach()).sum(-1).mean(),
            mu_pi=mu_pi,
            per_dim_at_bound=action_terms(model, mu_pi, std_pi, batch.actions, low_n, high_n),
        )  # fmt: skip

    t = in_precision(terms, dtype)(model, batch)
    per_dim, at_bound = t["per_dim_at_bound"]
    b = len(batch.actions)
    pi_bound = -(per_dim * at_bound).sum() / b
    pi_inside = -(per_dim * ~at_bound).sum() / b
    phi = list(model.posterior.parameters())
    out = {
        "e_pi_loss": float(t["e_pi"].detach()),
        "e_prior_loss": float(t["e_prior"]),
        "e_q_loss": float(t["e_q"]),
        "g_e_pi": _grad_norm(t["e_pi"], phi),
        "g_e_prior": _grad_norm(t["e_prior"], phi),
        "g_e_q": _grad_norm(t["e_q"], phi),
        "g_e_prior_wrt_z": float(torch.autograd.grad(t["e_prior"], t["z"], retain_graph=True)[0]
                                 .norm(dim=-1).mean()) * len(t["z"]),
        "g_e_pi_wrt_z": float(torch.autograd.grad(t["e_pi"], t["z"], retain_graph=True)[0]
                              .norm(dim=-1).mean()) * len(t["z"]),
        "e_pi_loss_at_bound": float(pi_bound),
        "e_pi_loss_inside": float(pi_inside),
        "g_e_pi_at_bound_wrt_z": float(torch.autograd.grad(pi_bound, t["z"], retain_graph=True)[0]
                                       .norm(dim=-1).mean()) * b,
        "g_e_pi_inside_wrt_z": float(torch.autograd.grad(pi_inside, t["z"], retain_graph=True)[0]
                                     .norm(dim=-1).mean()) * b,
        "g_m_pi": _grad_norm(t["m_pi"], list(model.policy.parameters())),
        "g_m_tawm": _grad_norm(t["m_tawm"], list(model.tawm.parameters())),
        "g_m_prior": _grad_norm(t["m_prior"], list(model.prior.parameters())),
        "m_prior_loss": float(t["m_prior"]),
        "m_tawm_loss": float(t["m_tawm"]),
    }  # fmt: skip
    with torch.no_grad():
        out |= {
            "abs_mu_q": float(t["mu_q"].abs().mean()),
            "abs_mu_p": float(t["mu_p"].abs().mean()),
            "mu_q_minus_p": float((t["mu_q"] - t["mu_p"]).abs().mean()),
            "log_std_q_mean": float(t["std_q"].log().mean()),
            "log_std_q_min": float(t["std_q"].log().min()),
            "log_std_p_mean": float(t["std_p"].log().mean()),
            "log_std_p_min": float(t["std_p"].log().min()),
            "log_std_p_max": float(t["std_p"].log().max()),
            "mahalanobis_z_prior": float(((t["z"] - t["mu_p"]) / t["std_p"]).pow(2).mean()),
            "log_std_pi_mean": float(t["std_pi"].log().mean()),
            "log_std_pi_min": float(t["std_pi"].log().min()),
            "log_std_tawm_mean": float(t["std_w"].log().mean()),
            "abs_mu_pi_max": float(t["mu_pi"].abs().max()),
            "share_at_bound": float(at_bound.float().mean()),
            "log_std_pi_at_bound": float(t["std_pi"].log()[at_bound].mean()),
            "log_std_pi_inside": float(t["std_pi"].log()[~at_bound].mean()),
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-S", "--set", dest="overrides", action="append", default=[])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--every", type=int, default=5, help="steps between traced steps")
    parser.add_argument("--val-every", type=int, default=50)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument(
        "--report", action="store_true", help="only rewrite the .md from the --out CSV there"
    )
    args = parser.parse_args()
    argv = [a for a in sys.argv[1:] if a != "--report"]
    if args.report:
        with args.out.open() as f:
            rows = [{k: float(v) for k, v in r.items() if v} for r in csv.DictReader(f)]
        for row in rows:
            row["step"] = int(row["step"])
        args.out.with_suffix(".md").write_text(markdown(rows, args, argv))
        return

    torch.set_num_threads(args.threads)
    params = load_params("params.yaml", args.overrides)
    cfg = params.train
    segments = load_segments(Paths().segments(params.ingest.name))
    # The same construction and seeding as stages.train._train (a fresh run, one process).
    torch.manual_seed(cfg.seed)
    model = SkillModel(model_config(cfg, segments))
    st = segments.stats
    model.set_normalization(st.state_mean, st.state_std, st.action_mean, st.action_std)
    updater = updater_for(cfg, model)
    device = torch.device("cpu")
    train = WindowSampler(segments, "train", device, seed=cfg.seed)
    val = WindowSampler(segments, "validation", device, seed=cfg.seed)
    val_idx = val.fixed_subset(cfg.val_windows, seed=cfg.seed)
    torch.manual_seed(cfg.seed)
    acts = torch.as_tensor(segments.actions)
    low_n, high_n = model.norm_actions(acts.min(0).values), model.norm_actions(acts.max(0).values)

    args.out.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    for step in range(1, args.steps + 1):
        batch = train.sample(cfg.batch_size)
        row: dict[str, float] = {"step": step}
        if step % args.every == 0 or step == 1:
            rng = torch.get_rng_state()
            row |= diagnose(model, batch, cfg.dtype, low_n, high_n)
            torch.set_rng_state(rng)
        metrics = updater.step(batch)
        if (step % args.every == 0) or step == 1:
            row |= {k: float(v) for k, v in metrics.items()}
        if step % args.val_every == 0:
            val_metrics = evaluate(model, val, val_idx)
            row |= {"val_st_nll_prior": val_metrics["val/st_nll_prior"],
                    "val_st_nll": val_metrics["val/st_nll"], "val_kl": val_metrics["val/kl"],
                    "val_action_nll": val_metrics["val/action_nll"]}  # fmt: skip
        if len(row) > 1:
            rows.append(row)
            if "val_st_nll_prior" in row:
                print(
                    f"step {step}: val st_nll_prior {row['val_st_nll_prior']:.3f} "
                    f"e_grad {row.get('e_grad_norm', float('nan')):.0f} "
                    f"|mu_q| {row.get('abs_mu_q', float('nan')):.2f}",
                    flush=True,
                )
    names = sorted({k for r in rows for k in r}, key=lambda k: (k != "step", k))
    with args.out.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=names)
        writer.writeheader()
        writer.writerows(rows)
    summary = args.out.with_suffix(".md")
    summary.write_text(markdown(rows, args, argv))
    print(f"wrote {args.out} ({len(rows)} rows) and {summary}")


SUMMARY = [  # (column, heading)
    ("val_st_nll_prior", "val s_T NLL, prior skills"),
    ("share_at_bound", "share of actions clipped"),
    ("e_pi_loss_at_bound", "-log pi, clipped actions"),
    ("e_pi_loss_inside", "-log pi, other actions"),
    ("log_std_pi_at_bound", "log std pi, clipped"),
    ("log_std_pi_inside", "log std pi, other"),
    ("g_e_pi_at_bound_wrt_z", "dz norm, clipped"),
    ("g_e_pi_inside_wrt_z", "dz norm, other"),
    ("abs_mu_q", "mean abs mu_q"),
    ("log_std_q_mean", "log std q"),
    ("log_std_p_mean", "log std prior"),
    ("e_grad_norm", "E grad norm"),
    ("m_grad_norm", "M grad norm"),
]


def markdown(rows: list[dict], args: argparse.Namespace, argv: list[str]) -> str:
    """The trace at each validation step (training terms on that step's batch)."""
    from runs_report import this_machine  # scripts/ is the script's own folder on sys.path

    commit = code_version(Path.cwd()) or "unknown"
    lines = [
        f"# EM trace: {' '.join(argv)}",
        "",
        f"Written by `scripts/em_trace.py` (every traced step: `{args.out.name}`; `--report` "
        "rewrites this file from it). Commit "
        f"{commit or 'unknown'}; machine: {this_machine()}.",
        "",
        "Each row is the step's batch before its update; clipped actions are those at a bound "
        "of the data's action range; dz norm: the norm of -log pi's gradient with respect to z, "
        "summed over the batch.",
        "",
        "| step | " + " | ".join(h for _, h in SUMMARY) + " |",
        "|---" * (len(SUMMARY) + 1) + "|",
    ]
    for row in rows:
        if "val_st_nll_prior" in row:
            cells = [f"{row[c]:.3g}" if c in row else "" for c, _ in SUMMARY]
            lines.append(f"| {row['step']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
