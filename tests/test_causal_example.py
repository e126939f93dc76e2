"""Appendix B numbers: equal ELBOs, an E-step objective that separates the models, and planning."""

import dataclasses
import math
from fractions import Fraction as F

import pytest
from typer.testing import CliRunner

from cli import app
from pipeline.analysis.causal_example import (
    ACTION_VALUES,
    PAPER_MISPRINTS,
    TabularSkillModel,
    causal_posterior,
    correct_model,
    data_distribution,
    e_step_kl,
    e_step_loss,
    elbo,
    elbo_gap,
    expected_log_likelihood,
    incorrect_model,
    m_step_optimum,
    model_joint,
    plan,
    transition_noise_entropy,
    true_values,
)

DATA = data_distribution()
# -H(a, s') of the data: p = 1/3, 1/30, 3/10, 1/3 (derived by hand, independent of the module).
ELBO_BY_HAND = -(2 / 3 * math.log(3) + 1 / 30 * math.log(30) + 3 / 10 * math.log(10 / 3))
# Incorrect model: KL at (a2, s2) is log(1 / (1/10)), at (a2, s3) log(1 / (9/10)), else 0.
KL_BY_HAND = 1 / 30 * math.log(10) + 3 / 10 * math.log(10 / 9)
MODELS = {"correct": correct_model(), "incorrect": incorrect_model()}


def test_data_distribution_is_uniform_actions_through_the_mdp():
    assert data_distribution() == {
        (0, 1): F(1, 3),
        (1, 2): F(1, 30),
        (1, 3): F(3, 10),
        (2, 3): F(1, 3),
    }
    assert sum(DATA.values()) == 1


def test_tables_match_the_paper():
    c, i = MODELS["correct"], MODELS["incorrect"]
    one_hot = [(1, 0, 0), (0, 1, 0), (0, 0, 1)]
    assert [c.posterior[t] for t in sorted(DATA)] == [one_hot[a] for a, _ in sorted(DATA)]
    assert list(c.policy) == one_hot
    assert c.tawm == ((0, 1, 0, 0), (0, 0, F(1, 10), F(9, 10)), (0, 0, 0, 1))
    assert c.prior == (F(1, 3),) * 3
    assert [i.posterior[t] for t in sorted(DATA)] == [one_hot[s - 1] for _, s in sorted(DATA)]
    assert i.policy == ((1, 0, 0), (0, 1, 0), (0, F(9, 19), F(10, 19)))
    assert i.tawm == ((0, 1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1))
    assert i.prior == (F(1, 3), F(1, 30), F(19, 30))


@pytest.mark.parametrize("name", MODELS)
def test_every_table_is_a_normalized_distribution(name):
    m = MODELS[name]
    rows = [m.prior, *m.policy, *m.tawm, *m.posterior.values()]
    assert all(sum(row) == 1 and min(row) >= 0 for row in rows)
    assert set(m.posterior) == set(DATA)


@pytest.mark.parametrize(
    ("misprint", "field", "model"),
    [("table 7, p(s'|z=3)", "tawm", "correct"), ("table 10, pi(a|z=3)", "policy", "incorrect")],
)
def test_rows_as_printed_in_the_paper_are_not_distributions(misprint, field, model):
    printed, corrected = PAPER_MISPRINTS[misprint]
    m = MODELS[model]
    assert getattr(m, field)[2] == corrected
    rows = (*getattr(m, field)[:2], printed)
    with pytest.raises(ValueError, match=r"row z=3 .* is not a distribution"):
        dataclasses.replace(m, **{field: rows})


@pytest.mark.parametrize("name", MODELS)
def test_corrected_tables_are_the_m_step_optimum_for_each_posterior(name):
    m = MODELS[name]
    assert m_step_optimum(m.posterior, DATA) == (m.policy, m.tawm, m.prior)


@pytest.mark.parametrize("name", MODELS)
def test_both_models_reproduce_the_data_distribution_exactly(name):
    assert model_joint(MODELS[name]) == DATA


def test_elbos_are_equal_and_match_the_hand_derived_and_paper_values():
    correct, incorrect = (elbo(m, DATA) for m in MODELS.values())
    assert correct == pytest.approx(incorrect, abs=1e-14)
    assert correct == pytest.approx(ELBO_BY_HAND, rel=1e-13)
    assert round(correct, 5) == -1.20697  # appendix B, compute_elbo.py


@pytest.mark.parametrize("name", MODELS)
def test_the_bound_is_tight_for_both_models(name):
    m = MODELS[name]
    assert elbo_gap(m, DATA) == 0.0
    assert elbo(m, DATA) == pytest.approx(expected_log_likelihood(m, DATA), abs=1e-14)


def test_elbo_is_log_likelihood_minus_gap_for_an_inexact_posterior():
    """On a model with full support and a posterior that is not its own, the bound is strict."""
    m = TabularSkillModel(
        "generic",
        posterior={t: (F(1, 2), F(1, 3), F(1, 6)) for t in DATA},
        policy=((F(1, 2), F(1, 4), F(1, 4)), (F(1, 5), F(3, 5), F(1, 5)), (F(1, 3),) * 3),
        tawm=((0, F(1, 2), F(1, 4), F(1, 4)), (0, F(1, 10), F(1, 10), F(4, 5)), (0, 0, 0, 1)),
        prior=(F(1, 4), F(1, 4), F(1, 2)),
    )
    gap = elbo_gap(m, DATA)
    assert gap > 0.01
    assert elbo(m, DATA) == pytest.approx(expected_log_likelihood(m, DATA) - gap, abs=1e-14)


def test_causal_posteriors_follow_eq_14():
    assert [causal_posterior(MODELS["correct"], a) for a in range(3)] == [
        (1, 0, 0),
        (0, 1, 0),
        (0, 0, 1),
    ]
    incorrect = [causal_posterior(MODELS["incorrect"], a) for a in range(3)]
    assert incorrect == [(1, 0, 0), (0, F(1, 10), F(9, 10)), (0, 0, 1)]


def test_e_step_objective_separates_the_models():
    assert e_step_kl(MODELS["correct"], DATA) == 0.0
    kl = e_step_kl(MODELS["incorrect"], DATA)
    assert kl == pytest.approx(KL_BY_HAND, rel=1e-13)
    assert kl == pytest.approx(0.1083610, abs=1e-7)
    # It is the environment's noise H(s'|a) = H_b(0.1) / 3 that the incorrect z has absorbed.
    assert kl == pytest.approx(transition_noise_entropy(DATA), rel=1e-13)
    binary_entropy = -(0.1 * math.log(0.1) + 0.9 * math.log(0.9))
    assert kl == pytest.approx(binary_entropy / 3, rel=1e-13)


@pytest.mark.parametrize("name", MODELS)
def test_e_step_loss_is_the_kl_plus_log_3(name):
    """Eq. 15 differs from the KL by -E log eta; both models have p(a) = 1/3, so eta = 1/3."""
    m = MODELS[name]
    assert e_step_loss(m, DATA) == pytest.approx(e_step_kl(m, DATA) + math.log(3), rel=1e-13)


def test_zero_posterior_mass_is_skipped_but_impossible_mass_is_infinite():
    m = MODELS["correct"]
    posterior = dict(m.posterior)
    posterior[0, 1] = (0, 1, 0)  # skill 2 never takes a1
    bad = dataclasses.replace(m, posterior=posterior)
    assert elbo(bad, DATA) == -math.inf
    assert e_step_kl(bad, DATA) == math.inf
    assert math.isfinite(elbo(m, DATA))  # the zeros of the one-hot posterior are 0 log 0 = 0


def test_action_values_come_from_the_mdp():
    # The paper says a2 is worth -89 in expectation; 0.1 * 100 + 0.9 * (-100) is -80.
    assert ACTION_VALUES == (10, -80, -100)


def test_correct_model_plans_z1_and_is_right():
    decision = plan(MODELS["correct"])
    assert (decision.skill, decision.believed, decision.true) == (0, 10, 10)
    assert true_values(MODELS["correct"]) == (10, -80, -100)


def test_incorrect_model_plans_z2_believing_100_and_gets_minus_80():
    decision = plan(MODELS["incorrect"])
    assert (decision.skill, decision.believed, decision.true) == (1, 100, -80)
    assert true_values(MODELS["incorrect"]) == (10, -80, F(-1720, 19))


def test_cli_prints_the_report():
    result = CliRunner().invoke(app, ["causal-example"])
    assert result.exit_code == 0, result.output
    out = result.output
    assert out.count("ELBO (eq. 1)                   -1.206973") == 2
    assert "E-step KL to eq. 14 posterior  +0.000000" in out
    assert "E-step KL to eq. 14 posterior  +0.108361" in out
    assert "plans z=1: expects 10, really gets 10" in out
    assert "plans z=2: expects 100, really gets -80" in out
    assert "table 10, pi(a|z=3) printed (0, 9/19, 11/19), used (0, 9/19, 10/19)" in out
