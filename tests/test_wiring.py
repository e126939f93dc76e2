"""Wiring of the objectives (paper eqs. 1, 15, 16) with random weights, against independent code.

The reference values here are built from the four networks' raw `(mean, std)` outputs with
`torch.distributions` and explicit loops over the window, not from `pipeline.training.losses`: the
policy sees s_0..s_{T-1} step by step, the prior and TAWM see s_0, the TAWM scores s_T, the KL is
the closed form of KL(q || p_omega). With random weights every network input matters, so feeding
the wrong state, flipping the KL or averaging over the wrong axis changes the numbers.
Everything runs in float64 so agreement can be asked to 1e-10.
"""

import copy

import pytest
import torch
from factories import skill_model_config, train_updater
from torch.distributions import Normal

from pipeline.model import SkillModel
from pipeline.training.data import WindowBatch
from pipeline.training.losses import (
    e_objective,
    e_objective_closed_form,
    e_step_loss,
    m_objective,
    m_step_loss,
    vi_loss,
    vi_objective,
)

B, T, SD, AD, ZD = 5, 4, 3, 2, 4
TOL = {"rtol": 1e-10, "atol": 1e-10}


def _model(seed: int = 0, z_dim: int = ZD) -> SkillModel:
    """Random weights and biases (biases too: torch's default init leaves them small but the
    std heads' softplus would then be nearly the same everywhere) and a non-trivial
    normalization, which the losses must not apply again to the already normalized batch."""
    torch.manual_seed(seed)
    # The paper's GRU posterior: with these weights its q stays within the E-loss test's grid.
    config = skill_model_config(SD, AD, z_dim=z_dim, hidden=8, tawm_shared_std=False, encoder="gru")
    model = SkillModel(config)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(0.5 * torch.randn_like(p))
    model.set_normalization([1.0, -2.0, 0.5], [2.0, 0.5, 3.0], [0.3, -0.1], [0.7, 1.5])
    return model.double()


def _batch(seed: int = 1) -> WindowBatch:
    g = torch.Generator().manual_seed(seed)
    return WindowBatch(
        states=torch.randn(B, T + 1, SD, generator=g, dtype=torch.float64),
        actions=torch.randn(B, T, AD, generator=g, dtype=torch.float64),
    )


def _z(seed: int = 2) -> torch.Tensor:
    return torch.randn(B, ZD, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


# -- the independent reference ---------------------------------------------------------------
def _gauss(mean_std: tuple[torch.Tensor, torch.Tensor]) -> Normal:
    return Normal(*mean_std)


def _posterior(model: SkillModel, batch: WindowBatch) -> Normal:
    """q_phi(z | s_0..T-1, a_0..T-1), per dimension: `[B, z]`."""
    return _gauss(model.posterior(batch.states[:, :T], batch.actions))


def _log_terms(model: SkillModel, batch: WindowBatch, z: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-window `[B]` log pi(a_0..T-1 | s_0..T-1, z), log p_psi(s_T | s_0, z),
    log p_omega(z | s_0), each summed over its dimensions (and pi over the T steps)."""
    s0, s_end = batch.states[:, 0], batch.states[:, T]
    log_pi = torch.zeros(B, dtype=torch.float64)
    for t in range(T):
        pi_t = _gauss(model.policy(torch.cat([batch.states[:, t], z], dim=-1)))
        log_pi = log_pi + pi_t.log_prob(batch.actions[:, t]).sum(-1)
    tawm = _gauss(model.tawm(torch.cat([s0, z], dim=-1)))
    prior = _gauss(model.prior(s0))
    return {
        "log_pi": log_pi,
        "log_tawm": tawm.log_prob(s_end).sum(-1),
        "log_prior": prior.log_prob(z).sum(-1),
    }


def _eq15(model, batch, z):
    """-1/B sum_i [log pi + log p_omega(z|s_0) - log q(z|tau)]."""
    r = _log_terms(model, batch, z)
    log_q = _posterior(model, batch).log_prob(z).sum(-1)
    return -(r["log_pi"] + r["log_prior"] - log_q).sum() / B


def _eq16(model, batch, z):
    """-1/B sum_i [log pi + log p_psi(s_T|s_0,z) + log p_omega(z|s_0)]."""
    r = _log_terms(model, batch, z)
    return -(r["log_pi"] + r["log_tawm"] + r["log_prior"]).sum() / B


def _kl_q_prior(model, batch) -> torch.Tensor:
    """KL(q(z|tau) || p_omega(z|s_0)) `[B]`, closed form for diagonal Gaussians."""
    q = _posterior(model, batch)
    p = _gauss(model.prior(batch.states[:, 0]))
    mq, sq, mp, sp = q.loc, q.scale, p.loc, p.scale
    kl = torch.log(sp / sq) + (sq**2 + (mq - mp) ** 2) / (2 * sp**2) - 0.5
    return kl.sum(-1)


def _eq1(model, batch, z):
    """Negative ELBO: -1/B sum_i [log pi + log p_psi(s_T|s_0,z) - KL(q || p_omega)]."""
    r = _log_terms(model, batch, z)
    return -(r["log_pi"] + r["log_tawm"] - _kl_q_prior(model, batch)).sum() / B


def _rsample_z(model, batch, seed) -> torch.Tensor:
    """The z the implementation draws after `torch.manual_seed(seed)`: q.rsample() draws its
    standard normal noise exactly like `torch.randn` (checked in the test below)."""
    q = _posterior(model, batch)
    torch.manual_seed(seed)
    return q.loc + q.scale * torch.randn(B, q.loc.shape[-1], dtype=torch.float64)


# -- objectives at given z -------------------------------------------------------------------
def test_eq15_e_objective_matches_the_independent_computation():
    model, batch, z = _model(), _batch(), _z()
    q = model.posterior_dist(batch.states[:, :-1], batch.actions)
    torch.testing.assert_close(e_objective(model, batch, q, z), _eq15(model, batch, z), **TOL)


def _eq15_closed_form(model, batch, z):
    """-1/B sum_i [log pi - KL(q || p_omega)] (`train.e_kl: closed_form`)."""
    r = _log_terms(model, batch, z)
    return -(r["log_pi"] - _kl_q_prior(model, batch)).sum() / B


def test_eq15_closed_form_e_objective_matches_the_independent_computation():
    model, batch, z = _model(), _batch(), _z()
    q = model.posterior_dist(batch.states[:, :-1], batch.actions)
    got = e_objective_closed_form(model, batch, q, z)
    torch.testing.assert_close(got, _eq15_closed_form(model, batch, z), **TOL)
    assert abs(got - e_objective(model, batch, q, z)) > 1e-3  # another estimator at one z


def test_eq15_closed_form_and_sampled_kl_agree_in_expectation_over_z():
    """Over many z ~ q the two E objectives average to the same value (log q - log p at z ~ q
    averages to the KL), so `e_kl` changes the noise of the E-step, not its objective."""
    model, batch = _model(), _batch()
    q = model.posterior_dist(batch.states[:, :-1], batch.actions)
    with torch.no_grad():
        diffs = torch.stack([
            e_objective(model, batch, q, z) - e_objective_closed_form(model, batch, q, z)
            for z in q.sample((4000,))
        ])  # fmt: skip
    assert diffs.std() > 0.1  # the sampled KL is noisy at one z
    assert abs(diffs.mean()) < 4 * diffs.std() / 4000**0.5


def test_e_step_loss_with_the_closed_form_kl():
    model, batch = _model(), _batch()
    torch.manual_seed(7)
    loss, _ = e_step_loss(model, batch, kl="closed_form")
    want = _eq15_closed_form(model, batch, _rsample_z(model, batch, seed=7))
    torch.testing.assert_close(loss, want, **TOL)


def test_eq16_m_objective_and_its_terms_match_the_independent_computation():
    model, batch, z = _model(), _batch(), _z()
    loss, terms = m_objective(model, batch, z)
    torch.testing.assert_close(loss, _eq16(model, batch, z), **TOL)
    for name, want in _log_terms(model, batch, z).items():
        torch.testing.assert_close(terms[name], want, **TOL, msg=name)


def test_eq1_vi_objective_and_its_kl_match_the_independent_computation():
    model, batch, z = _model(), _batch(), _z()
    q = model.posterior_dist(batch.states[:, :-1], batch.actions)
    loss, terms = vi_objective(model, batch, q, z)
    torch.testing.assert_close(terms["kl"], _kl_q_prior(model, batch), **TOL)
    torch.testing.assert_close(loss, _eq1(model, batch, z), **TOL)


# -- the losses with z ~ q -------------------------------------------------------------------
def test_the_losses_sample_z_from_the_posterior_of_s0_to_sT_minus_1():
    model, batch = _model(), _batch()
    q = _posterior(model, batch)
    torch.manual_seed(5)
    rsampled = torch.distributions.Independent(q, 1).rsample()
    torch.manual_seed(5)
    assert torch.equal(rsampled, q.loc + q.scale * torch.randn_like(q.loc))  # see _rsample_z

    for loss_fn, reference in ((e_step_loss, _eq15), (m_step_loss, _eq16), (vi_loss, _eq1)):
        torch.manual_seed(7)
        loss, metrics = loss_fn(model, batch)
        want = reference(model, batch, _rsample_z(model, batch, seed=7))
        torch.testing.assert_close(loss, want, **TOL, msg=loss_fn.__name__)
        assert next(iter(metrics.values())) == pytest.approx(want.item(), rel=1e-10)


# -- what the updaters differentiate -----------------------------------------------------------
def _grads(loss: torch.Tensor, params: list[torch.nn.Parameter]) -> list[torch.Tensor]:
    return list(torch.autograd.grad(loss, params))


def _assert_grads_equal(got_params, want_grads, what):
    assert len(got_params) == len(want_grads)
    for i, (p, g) in enumerate(zip(got_params, want_grads, strict=True)):
        assert p.grad is not None, f"{what}: parameter {i} got no gradient"
        torch.testing.assert_close(p.grad, g, **TOL, msg=f"{what}: parameter {i}")


def test_em_step_with_the_closed_form_kl_differentiates_it_in_phi():
    model, batch = _model(), _batch()
    ref = copy.deepcopy(model)
    torch.manual_seed(3)
    train_updater(model, lr_e=1e-2, lr_m=1e-2, e_kl="closed_form", e_prior="current").e_step(batch)
    z_e = _rsample_z(ref, batch, seed=3)
    want = _grads(_eq15_closed_form(ref, batch, z_e), list(ref.posterior.parameters()))
    _assert_grads_equal(list(model.posterior.parameters()), want, "E-step, closed-form KL")


def test_em_step_differentiates_eq15_in_phi_through_z_then_eq16_in_theta_psi_omega():
    """One `EMUpdater.step`: the E-step's gradient (left in phi's .grad) is d(eq. 15)/d(phi) with
    z reparameterized, so it flows through z too; then the M-step's (left in theta, psi, omega)
    is d(eq. 16) at z drawn from the posterior *after* the E-step's update, at the generative
    parameters as they were before any update."""
    model, batch = _model(), _batch()
    before = copy.deepcopy(model)
    updater = train_updater(model, lr_e=1e-2, lr_m=1e-2, e_prior="current")
    torch.manual_seed(3)
    updater.step(batch)

    ref = copy.deepcopy(before)
    z_e = _rsample_z(ref, batch, seed=3)
    want_e = _grads(_eq15(ref, batch, z_e), list(ref.posterior.parameters()))
    _assert_grads_equal(list(model.posterior.parameters()), want_e, "E-step")

    # M reference: phi as the E-step left it, theta/psi/omega as before; the E-step's noise drawn
    # first, then the M-step's from the same stream.
    ref = copy.deepcopy(before)
    ref.posterior.load_state_dict(model.posterior.state_dict())
    torch.manual_seed(3)
    torch.randn(B, ZD, dtype=torch.float64)  # the E-step's draw
    q = _posterior(ref, batch)
    z_m = (q.loc + q.scale * torch.randn(B, ZD, dtype=torch.float64)).detach()
    want_m = _grads(_eq16(ref, batch, z_m), ref.generative())
    _assert_grads_equal(model.generative(), want_m, "M-step")
    assert not any(
        torch.equal(a, b) for a, b in zip(model.generative(), before.generative(), strict=True)
    ), "the M-step did not update theta, psi, omega"


def test_vi_step_differentiates_eq1_in_all_parameters_jointly():
    model, batch = _model(), _batch()
    ref = copy.deepcopy(model)
    want = _grads(_eq1(ref, batch, _rsample_z(ref, batch, seed=6)), list(ref.parameters()))
    torch.manual_seed(6)
    train_updater(model, method="vi", lr_m=1e-2).step(batch)
    _assert_grads_equal(list(model.parameters()), want, "VI step")


# -- eq. 15 is the KL to the causal posterior (eq. 2), up to log eta -------------------------
def test_expected_e_loss_is_the_kl_to_the_causal_posterior_minus_log_eta():
    """With a 1-d z the causal posterior p(z|s,a) = pi(a|s,z) p_omega(z|s_0) / eta (eq. 2) is
    computable on a grid. E_q[eq. 15] must equal mean_i[KL(q_i || p_i) - log eta_i]. The
    expectation over q of the implementation's `e_objective` is the mean over G equal-probability
    quantiles of each q_i (one batch of B * G windows); KL and eta come from the trapezoid rule
    on a grid, with the causal posterior built here from the raw networks."""
    model, batch = _model(z_dim=1), _batch()
    n_q = 20_000  # quantiles per window (Gauss-Hermite is inaccurate: ReLU kinks in log pi)
    unit = torch.special.ndtri((torch.arange(n_q, dtype=torch.float64) + 0.5) / n_q)
    rep = WindowBatch(
        batch.states.repeat_interleave(n_q, dim=0), batch.actions.repeat_interleave(n_q, dim=0)
    )
    with torch.no_grad():
        q = model.posterior_dist(rep.states[:, :-1], rep.actions)
        expected_loss = e_objective(model, rep, q, q.mean + q.stddev * unit.repeat(B)[:, None])

        grid = torch.linspace(-12.0, 12.0, 40_001, dtype=torch.float64)  # [G]
        zg = grid[:, None, None].expand(-1, B, 1)  # [G, B, 1]
        states = batch.states[None].expand(len(grid), -1, -1, -1)
        log_joint = torch.zeros(len(grid), B, dtype=torch.float64)  # log pi + log p_omega
        for t in range(T):
            pi_t = _gauss(model.policy(torch.cat([states[:, :, t], zg], dim=-1)))
            log_joint = log_joint + pi_t.log_prob(batch.actions[None, :, t]).sum(-1)
        prior = _gauss(model.prior(batch.states[:, 0]))
        log_joint = log_joint + prior.log_prob(zg).sum(-1)
        log_eta = torch.logsumexp(log_joint, dim=0) + torch.log(grid[1] - grid[0])
        log_causal = log_joint - log_eta  # [G, B], integrates to 1
        q_b = _posterior(model, batch)
        log_q = Normal(q_b.loc[:, 0], q_b.scale[:, 0]).log_prob(grid[:, None])  # [G, B]
        kl = torch.trapezoid(log_q.exp() * (log_q - log_causal), grid, dim=0)
    assert float(torch.trapezoid(log_causal.exp(), grid, dim=0).min()) == pytest.approx(1, 1e-6)
    assert float(torch.trapezoid(log_q.exp(), grid, dim=0).min()) == pytest.approx(1, 1e-6)
    torch.testing.assert_close(expected_loss, (kl - log_eta).mean(), rtol=1e-5, atol=0)
