"""The E, M and naive-VI objectives (paper eqs. 1, 15, 16) and validation metrics.

Log-likelihoods are of normalized states/actions, summed over dimensions and (for the policy)
over the T steps of a window, then averaged over the batch, exactly as in eqs. 15-16.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.distributions import Independent, kl_divergence

from pipeline.model.skill_model import SkillModel, diag_normal
from pipeline.training.data import WindowBatch


def policy_log_prob(model: SkillModel, batch: WindowBatch, z: torch.Tensor) -> torch.Tensor:
    """log pi_theta(a_0..T-1 | s_0..T-1, z) `[B]`: sum over the T steps (censored at the action
    bounds when the model has them, `SkillModel.policy_log_prob`)."""
    s = batch.states[:, :-1]
    z_t = z[:, None, :].expand(-1, s.shape[1], -1)
    return model.policy_log_prob(s, z_t, batch.actions).sum(-1)


def _prior_dist(model: SkillModel, s0_n: torch.Tensor, prior: nn.Module | None) -> Independent:
    """p_omega(z | s_0): the model's prior, or the network `prior` in its place (an EMA copy)."""
    return model.prior_dist(s0_n) if prior is None else diag_normal(*prior(s0_n))


def e_objective(
    model: SkillModel,
    batch: WindowBatch,
    q: Independent,
    z: torch.Tensor,
    prior: nn.Module | None = None,
) -> torch.Tensor:
    """Eq. 15 for given posterior `q` and samples `z [B, z_dim]`:
    -mean[log pi(a|s,z) + log p_omega(z|s_0) - log q_phi(z|tau)] (`prior`: see `_prior_dist`)."""
    log_pi = policy_log_prob(model, batch, z)
    log_prior = _prior_dist(model, batch.states[:, 0], prior).log_prob(z)
    return -(log_pi + log_prior - q.log_prob(z)).mean()


def e_objective_closed_form(
    model: SkillModel,
    batch: WindowBatch,
    q: Independent,
    z: torch.Tensor,
    prior: nn.Module | None = None,
) -> torch.Tensor:
    """Eq. 15 with the KL to the prior in closed form: -mean[log pi(a|s,z) - KL(q || p_omega)].
    Equal to `e_objective` in expectation over z ~ q, with less noise."""
    kl = kl_divergence(q, _prior_dist(model, batch.states[:, 0], prior))
    return -(policy_log_prob(model, batch, z) - kl).mean()


E_OBJECTIVES = {"sampled": e_objective, "closed_form": e_objective_closed_form}


def e_step_loss(
    model: SkillModel, batch: WindowBatch, kl: str = "sampled", prior: nn.Module | None = None
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Eq. 15 with z ~ q_phi reparameterized; `kl` (`train.e_kl`): the KL to the prior at the
    drawn z (`sampled`, as the paper's code) or in closed form (`closed_form`, as `vi_loss`);
    `prior`: a network standing in for the model's prior (`train.e_prior: ema`), or None.

    Minimizing it over phi alone minimizes KL(q_phi || p(z|s,a)), the causal posterior of
    eq. 2; no TAWM term, so q cannot encode where the window ends beyond what the actions say.
    """
    q = model.posterior_dist(batch.states[:, :-1], batch.actions)
    loss = E_OBJECTIVES[kl](model, batch, q, q.rsample(), prior)
    return loss, {"e_loss": loss.detach()}


def m_objective(
    model: SkillModel, batch: WindowBatch, z: torch.Tensor
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Eq. 16 for given skills `z [B, z_dim]`:
    -mean[log pi(a|s,z) + log p_psi(s_T|s_0,z) + log p_omega(z|s_0)], and its terms `[B]`."""
    s0 = batch.states[:, 0]
    terms = {
        "log_pi": policy_log_prob(model, batch, z),
        "log_tawm": model.tawm_dist(s0, z).log_prob(batch.states[:, -1]),
        "log_prior": model.prior_dist(s0).log_prob(z),
    }
    return -sum(terms.values()).mean(), terms


def m_step_loss(
    model: SkillModel, batch: WindowBatch
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Eq. 16 with z ~ q_phi (the posterior just updated by the E-step).

    z is sampled without gradient: the M-step updates theta, psi and omega only, and none of
    their gradients flows through z.

    With the windows that follow (`batch.after_states`, `train.tawm_chain` K > 1) the TAWM
    term is `chained_tawm_log_prob`'s, averaged over the K skills; the policy and prior terms
    stay the first window's. One window: eq. 16 exactly.
    """
    if batch.after_states is not None:
        return _chained_m_step_loss(model, batch)
    with torch.no_grad():
        z = model.posterior_dist(batch.states[:, :-1], batch.actions).rsample()
    loss, terms = m_objective(model, batch, z)
    return loss, {
        "m_loss": loss.detach(),
        "action_nll": -terms["log_pi"].detach().mean(),
        "st_nll": -terms["log_tawm"].detach().mean(),
        "prior_nll": -terms["log_prior"].detach().mean(),
    }


def chained_tawm_log_prob(
    model: SkillModel, s0_n: torch.Tensor, z: torch.Tensor, outcomes: torch.Tensor
) -> torch.Tensor:
    """`[B, K]`: log p_psi(s_kT | s^_(k-1)T, z_k) of K skills chained as a planner chains them:
    s^_0 = s_0, then each next start is the TAWM's own prediction (`tawm_outcome`, its mean),
    with gradient through the chain, so the TAWM learns from the errors it feeds itself.
    `s0_n [B, sd]`, `z [B, K, z]`, `outcomes [B, K, sd]` the real s_T, s_2T, ... (normalized).
    """
    start, logs = s0_n, []
    for k in range(z.shape[1]):
        logs.append(model.tawm_dist(start, z[:, k]).log_prob(outcomes[:, k]))
        start = model.tawm_outcome(start, z[:, k])[0]
    return torch.stack(logs, dim=1)


def _chained_m_step_loss(
    model: SkillModel, batch: WindowBatch
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """`m_step_loss` over a window and the K - 1 that follow it."""
    assert batch.after_actions is not None
    states = torch.cat([batch.states, batch.after_states], dim=1)  # [B, KT + 1, sd]
    actions = torch.cat([batch.actions, batch.after_actions], dim=1)  # [B, KT, ad]
    b, t = batch.actions.shape[:2]
    k = actions.shape[1] // t
    with torch.no_grad():  # every window's skill, in one pass of the posterior
        windows = states[:, : k * t].reshape(b * k, t, -1)
        z = model.posterior_dist(windows, actions.reshape(b * k, t, -1)).rsample()
        z = z.reshape(b, k, -1)
    s0 = batch.states[:, 0]
    log_pi = policy_log_prob(model, batch, z[:, 0])
    log_prior = model.prior_dist(s0).log_prob(z[:, 0])
    log_tawm = chained_tawm_log_prob(model, s0, z, states[:, t::t])  # [B, K]
    loss = -(log_pi + log_tawm.mean(dim=1) + log_prior).mean()
    return loss, {
        "m_loss": loss.detach(),
        "action_nll": -log_pi.detach().mean(),
        "st_nll": -log_tawm[:, 0].detach().mean(),
        "st_nll_chained": -log_tawm[:, 1:].detach().mean(),
        "prior_nll": -log_prior.detach().mean(),
    }


def vi_objective(
    model: SkillModel, batch: WindowBatch, q: Independent, z: torch.Tensor
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Negative ELBO of eq. 1 for given `q` and samples `z`, with the KL in closed form."""
    s0 = batch.states[:, 0]
    terms = {
        "log_pi": policy_log_prob(model, batch, z),
        "log_tawm": model.tawm_dist(s0, z).log_prob(batch.states[:, -1]),
        "kl": kl_divergence(q, model.prior_dist(s0)),
    }
    return -(terms["log_pi"] + terms["log_tawm"] - terms["kl"]).mean(), terms


def vi_loss(model: SkillModel, batch: WindowBatch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Eq. 1 over all parameters jointly, z ~ q reparameterized (the naive-VI baseline)."""
    q = model.posterior_dist(batch.states[:, :-1], batch.actions)
    loss, terms = vi_objective(model, batch, q, q.rsample())
    return loss, {
        "vi_loss": loss.detach(),
        "action_nll": -terms["log_pi"].detach().mean(),
        "st_nll": -terms["log_tawm"].detach().mean(),
        "kl": terms["kl"].detach().mean(),
    }


@torch.no_grad()
def prior_marginal_nll(
    model: SkillModel, s0_n: torch.Tensor, s_t_n: torch.Tensor, prior_eps: torch.Tensor
) -> torch.Tensor:
    """-log p(s_T | s_0) `[B]` with the skill drawn from the prior: a K-sample Monte Carlo
    estimate of -log E_{z ~ p_omega(z|s_0)} p_psi(s_T | s_0, z), z = mean + std * eps_k.

    What a planner that picks skills from the prior may expect: low when the real outcome is
    one the prior's skills predict, not only the one its own inferred skill explains.
    `prior_eps [K, z]` (fixed draws: every checkpoint is scored on the same skills).
    """
    prior = model.prior_dist(s0_n)
    z = prior.mean + prior.stddev * prior_eps[:, None]  # [K, B, z]
    s0_k = s0_n.expand(len(prior_eps), *s0_n.shape)
    log_p = model.tawm_dist(s0_k, z).log_prob(s_t_n)  # [K, B]
    return math.log(len(prior_eps)) - torch.logsumexp(log_p, dim=0)


def validation_metrics(
    model: SkillModel, batch: WindowBatch, prior_eps: torch.Tensor | None = None
) -> dict[str, torch.Tensor]:
    """Per-window validation terms `[B]`, with z = the posterior mean (deterministic).

    Returns action NLL per step, s_T NLL, KL(q || p_omega), and s_T errors in raw state units:
    the TAWM mean given the posterior skill, given the prior-mean skill, and the no-model
    baseline that predicts s_T = s_0. With `prior_eps [K, z]`, also `st_nll_prior`, the s_T NLL
    with the skill marginalized over the prior (`prior_marginal_nll`).
    """
    q = model.posterior_dist(batch.states[:, :-1], batch.actions)
    z = q.mean
    s0, s_t = batch.states[:, 0], batch.states[:, -1]
    prior = model.prior_dist(s0)
    horizon = batch.actions.shape[1]
    std = model.state_std

    def raw_error(pred_n: torch.Tensor) -> torch.Tensor:
        return ((pred_n - s_t) * std).norm(dim=-1)

    metrics = {
        "action_nll": -policy_log_prob(model, batch, z) / horizon,
        "st_nll": -model.tawm_dist(s0, z).log_prob(s_t),
        "kl": kl_divergence(q, prior),
        "st_error": raw_error(model.tawm_outcome(s0, z)[0]),
        "st_error_prior_mean": raw_error(model.tawm_outcome(s0, prior.mean)[0]),
        "st_error_no_model": raw_error(s0),
    }
    if prior_eps is not None:
        metrics["st_nll_prior"] = prior_marginal_nll(model, s0, s_t, prior_eps)
    return metrics
