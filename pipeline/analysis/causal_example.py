"""Appendix B of the paper, as code: why the naive ELBO cannot tell a causal skill model from one
that has absorbed the environment's noise into z, and how the E-step objective can.

The MDP (appendix B, Fig. 8) has one step. From s0 the agent picks an action:

- a1 -> s1 (reward +10) with probability 1;
- a2 -> s2 (+100) with probability 0.1, or s3 (-100) with probability 0.9;
- a3 -> s3 (-100) with probability 1.

The data are one-step transitions under uniformly random actions, so the data distribution is
p(a1, s1) = 1/3, p(a2, s2) = 1/30, p(a2, s3) = 3/10, p(a3, s3) = 1/3. A skill model has three
discrete skills z in {1, 2, 3}: a posterior q(z | a, s'), a policy pi(a | z), a TAWM p(s' | z) and a
prior p(z) (s = s0 always, so dependence on s is dropped, as in the paper's tables).

Every table is held as exact `Fraction`s; log-quantities are float64 sums that skip zero-probability
terms (0 log 0 = 0) and are -inf / +inf where a support condition fails.

Transcription errors in the paper's text, and the values used here instead:

- Table 7, row z=3, is printed p(s' | z=3) = (0, 0, 0, 0.1), which sums to 0.1. In the correct
  model skill 3 is action a3 (table 6), and a3 leads to s3 with probability 1, so
  p(s' | z=3) = (0, 0, 0, 1). This is also the ELBO-maximizing TAWM for the correct posterior
  (`m_step_optimum`).
- Table 10, row z=3, is printed pi(a | z=3) = (0, 9/19, 11/19), which sums to 20/19. The incorrect
  posterior (table 9) sets z=3 exactly when s' = s3, so the ELBO-maximizing policy is
  pi(a | z=3) = p(a | s'=s3) = p(a, s3) / p(s3) = (0, (3/10) / (19/30), (1/3) / (19/30))
  = (0, 9/19, 10/19), consistent with table 12's p(z=3) = p(s3) = 19/30.

Two slips in the appendix prose: the expected reward of a2 is 0.1 * 100 + 0.9 * (-100) = -80, not
-89 (-89 is 0.1 * 10 + 0.9 * (-100)); and in the incorrect model skill z=2 is action a2 (table 10),
not a1.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from fractions import Fraction

Dist = tuple[Fraction, ...]
"""A distribution over a finite set, one exact probability per element."""
CondDist = tuple[Dist, ...]
"""A conditional distribution: one row (a `Dist`) per value of the conditioning variable."""
Transition = tuple[int, int]
"""An observed transition (action index, next-state index)."""

ACTIONS = ("a1", "a2", "a3")
NEXT_STATES = ("s0", "s1", "s2", "s3")
SKILLS = ("z=1", "z=2", "z=3")

F = Fraction
ZERO, ONE = F(0), F(1)
REWARD: tuple[Fraction, ...] = (ZERO, F(10), F(100), F(-100))
"""Reward on arriving in each next state s0..s3 (s0 is never reached)."""
DYNAMICS: CondDist = (
    (ZERO, ONE, ZERO, ZERO),
    (ZERO, ZERO, F(1, 10), F(9, 10)),
    (ZERO, ZERO, ZERO, ONE),
)
"""The true MDP, P(s' | s0, a): one row per action a1..a3, columns s0..s3."""
DATA_POLICY: Dist = (F(1, 3), F(1, 3), F(1, 3))
"""The demonstrator: actions chosen uniformly at random."""

PAPER_MISPRINTS: dict[str, tuple[Dist, Dist]] = {
    "table 7, p(s'|z=3)": ((ZERO, ZERO, ZERO, F(1, 10)), (ZERO, ZERO, ZERO, ONE)),
    "table 10, pi(a|z=3)": ((ZERO, F(9, 19), F(11, 19)), (ZERO, F(9, 19), F(10, 19))),
}
"""Rows as printed in the paper text, and as corrected (see the module docstring)."""


def _one_hot(index: int, size: int) -> Dist:
    return tuple(ONE if i == index else ZERO for i in range(size))


def _check_dist(row: Dist, size: int, what: str) -> None:
    if len(row) != size:
        raise ValueError(f"{what} has {len(row)} entries, expected {size}")
    if any(p < 0 for p in row) or sum(row) != 1:
        raise ValueError(f"{what} = {[str(p) for p in row]} is not a distribution (sum {sum(row)})")


def _log(p: Fraction) -> float:
    """log p for p >= 0, exact up to float64 rounding (log 0 = -inf)."""
    if p == 0:
        return -math.inf
    return math.log(p.numerator) - math.log(p.denominator)


def _kl(p: Dist, q: Dist) -> float:
    """KL(p || q) in nats, with 0 log 0 = 0; +inf where p puts mass outside q's support."""
    return sum(float(pi) * (_log(pi) - _log(qi)) for pi, qi in zip(p, q, strict=True) if pi > 0)


def data_distribution() -> dict[Transition, Fraction]:
    """p(a, s') of the uniformly random dataset, over its support only (four transitions)."""
    return {
        (a, s): DATA_POLICY[a] * DYNAMICS[a][s]
        for a in range(len(ACTIONS))
        for s in range(len(NEXT_STATES))
        if DATA_POLICY[a] * DYNAMICS[a][s] > 0
    }


@dataclass(frozen=True)
class TabularSkillModel:
    """A tabular one-step skill model (appendix B, tables 5-8 or 9-12).

    Attributes:
        name: Label used in reports.
        posterior: q(z | a, s') for every transition (a, s') in the data's support, a `Dist` over z.
        policy: pi(a | z), rows z=1..3, columns a1..a3.
        tawm: p(s' | z), rows z=1..3, columns s0..s3.
        prior: p(z) over z=1..3.
    """

    name: str
    posterior: Mapping[Transition, Dist]
    policy: CondDist
    tawm: CondDist
    prior: Dist

    def __post_init__(self) -> None:
        n_z = len(SKILLS)
        _check_dist(self.prior, n_z, f"{self.name} p(z)")
        for label, table, size in (
            ("pi(a|z)", self.policy, len(ACTIONS)),
            ("p(s'|z)", self.tawm, len(NEXT_STATES)),
        ):
            if len(table) != n_z:
                raise ValueError(f"{self.name} {label} has {len(table)} rows, expected {n_z}")
            for z, row in enumerate(table):
                _check_dist(row, size, f"{self.name} {label}, row {SKILLS[z]}")
        for (a, s), row in self.posterior.items():
            _check_dist(row, n_z, f"{self.name} q(z|{ACTIONS[a]},{NEXT_STATES[s]})")


def m_step_optimum(
    posterior: Mapping[Transition, Dist], data: Mapping[Transition, Fraction]
) -> tuple[CondDist, CondDist, Dist]:
    """The policy, TAWM and prior that maximize the ELBO (eq. 1) for a fixed posterior.

    With tabular models, eq. 1 splits into three expected log-likelihoods under the joint
    p(a, s') q(z | a, s'), each maximized by the matching conditional of that joint:
    p(z) = sum p(a, s') q(z | a, s'), pi(a | z) = sum_s' p(a, s') q(z | a, s') / p(z),
    p(s' | z) = sum_a p(a, s') q(z | a, s') / p(z).

    Returns:
        (policy, tawm, prior), exact.

    Raises:
        ValueError: The posterior never uses some skill, so its rows are undefined.
    """
    n_z = len(SKILLS)
    prior = [ZERO] * n_z
    policy = [[ZERO] * len(ACTIONS) for _ in range(n_z)]
    tawm = [[ZERO] * len(NEXT_STATES) for _ in range(n_z)]
    for (a, s), p in data.items():
        for z, qz in enumerate(posterior[a, s]):
            prior[z] += p * qz
            policy[z][a] += p * qz
            tawm[z][s] += p * qz
    if ZERO in prior:
        raise ValueError(f"the posterior never uses skill {SKILLS[prior.index(ZERO)]}")
    return (
        tuple(tuple(x / prior[z] for x in row) for z, row in enumerate(policy)),
        tuple(tuple(x / prior[z] for x in row) for z, row in enumerate(tawm)),
        tuple(prior),
    )


def correct_model() -> TabularSkillModel:
    """Tables 5-8: each skill is one action, the TAWM is the true dynamics of that action.

    q(z | a) = one-hot(a) (table 5), pi(a | z) = one-hot(z) (table 6), p(s' | z) = P(s' | a_z)
    (table 7, row z=3 corrected to s3 with probability 1), p(z) = 1/3 each (table 8).
    """
    posterior = {(a, s): _one_hot(a, len(SKILLS)) for a, s in data_distribution()}
    policy = tuple(_one_hot(z, len(ACTIONS)) for z in range(len(SKILLS)))
    tawm = (
        (ZERO, ONE, ZERO, ZERO),
        (ZERO, ZERO, F(1, 10), F(9, 10)),
        PAPER_MISPRINTS["table 7, p(s'|z=3)"][1],
    )
    return TabularSkillModel("correct", posterior, policy, tawm, (F(1, 3), F(1, 3), F(1, 3)))


def incorrect_model() -> TabularSkillModel:
    """Tables 9-12: the skill encodes the outcome s', so the TAWM is deterministic.

    q(z | s') = one-hot(s' index - 1) (table 9), pi(a | z) = p(a | s' = s_z) (table 10, row z=3
    corrected to (0, 9/19, 10/19)), p(s' | z) = one-hot(s_z) (table 11), p(z) = p(s' = s_z) =
    (1/3, 1/30, 19/30) (table 12).
    """
    posterior = {(a, s): _one_hot(s - 1, len(SKILLS)) for a, s in data_distribution()}
    policy = ((ONE, ZERO, ZERO), (ZERO, ONE, ZERO), PAPER_MISPRINTS["table 10, pi(a|z=3)"][1])
    tawm = tuple(_one_hot(z + 1, len(NEXT_STATES)) for z in range(len(SKILLS)))
    return TabularSkillModel("incorrect", posterior, policy, tawm, (F(1, 3), F(1, 30), F(19, 30)))


def model_joint(model: TabularSkillModel) -> dict[Transition, Fraction]:
    """The model's marginal p(a, s') = sum_z p(z) pi(a | z) p(s' | z), over its nonzero entries."""
    joint = {
        (a, s): sum(
            (model.prior[z] * model.policy[z][a] * model.tawm[z][s] for z in range(len(SKILLS))),
            ZERO,
        )
        for a in range(len(ACTIONS))
        for s in range(len(NEXT_STATES))
    }
    return {k: p for k, p in joint.items() if p > 0}


def expected_log_likelihood(model: TabularSkillModel, data: Mapping[Transition, Fraction]) -> float:
    """E_{p(a,s')} log p_model(a, s'), the left side of eqs. 3-4 (-inf if data fall off support)."""
    joint = model_joint(model)
    return sum(float(p) * _log(joint.get(t, ZERO)) for t, p in data.items())


def elbo(model: TabularSkillModel, data: Mapping[Transition, Fraction]) -> float:
    """Eq. 1 (= eq. 9) with the exact expectation over the data distribution, in nats.

        sum_{a,s'} p(a, s') sum_z q(z|a,s') [log pi(a|z) + log p(s'|z) + log p(z) - log q(z|a,s')].

    Terms with q = 0 contribute 0; a skill with q > 0 that gives the data probability 0 makes it
    -inf.
    """
    total = 0.0
    for (a, s), p in data.items():
        for z, qz in enumerate(model.posterior[a, s]):
            if qz > 0:
                log_joint = _log(model.policy[z][a]) + _log(model.tawm[z][s]) + _log(model.prior[z])
                total += float(p * qz) * (log_joint - _log(qz))
    return total


def exact_posterior(model: TabularSkillModel, transition: Transition) -> Dist:
    """The model's own posterior p(z|a,s') ∝ p(z) pi(a|z) p(s'|z); the ELBO is tight at it.

    Raises:
        ValueError: The model gives this transition probability 0.
    """
    a, s = transition
    weights = [model.prior[z] * model.policy[z][a] * model.tawm[z][s] for z in range(len(SKILLS))]
    evidence = sum(weights, ZERO)
    if evidence == 0:
        raise ValueError(f"{model.name}: p({ACTIONS[a]}, {NEXT_STATES[s]}) = 0")
    return tuple(w / evidence for w in weights)


def elbo_gap(model: TabularSkillModel, data: Mapping[Transition, Fraction]) -> float:
    """Jensen gap of eq. 9: E_{p(a,s')} KL(q(z|a,s') || p_model(z|a,s')) = log-likelihood - ELBO."""
    return sum(
        float(p) * _kl(model.posterior[t], exact_posterior(model, t)) for t, p in data.items()
    )


def causal_posterior(model: TabularSkillModel, action: int) -> Dist:
    """Eq. 2 / eq. 14 for T=1: p(z | s, a) = pi(a | z) p(z) / eta, which ignores s'.

    Raises:
        ValueError: No skill ever takes this action (eta = 0).
    """
    weights = [model.policy[z][action] * model.prior[z] for z in range(len(SKILLS))]
    eta = sum(weights, ZERO)
    if eta == 0:
        raise ValueError(f"{model.name}: no skill takes action {ACTIONS[action]}")
    return tuple(w / eta for w in weights)


def e_step_kl(model: TabularSkillModel, data: Mapping[Transition, Fraction]) -> float:
    """The E-step objective of §2.1: E_{p(a,s')} KL(q(z|a,s') || p(z|a)), p(z|a) from eq. 14.

    Zero exactly when q respects the causal structure of Fig. 6a (z influences s' only through a).
    """
    return sum(
        float(p) * _kl(model.posterior[a, s], causal_posterior(model, a))
        for (a, s), p in data.items()
    )


def e_step_loss(model: TabularSkillModel, data: Mapping[Transition, Fraction]) -> float:
    """Eq. 15 in expectation: E E_q[log q(z | a, s') - log pi(a | z) - log p(z)].

    Equals `e_step_kl` - E log eta(a) (appendix A, c = log eta): the loss actually minimized.
    """
    total = 0.0
    for (a, s), p in data.items():
        for z, qz in enumerate(model.posterior[a, s]):
            if qz > 0:
                log_causal = _log(model.policy[z][a]) + _log(model.prior[z])
                total += float(p * qz) * (_log(qz) - log_causal)
    return total


def transition_noise_entropy(data: Mapping[Transition, Fraction]) -> float:
    """H(s' | a) of the data in nats: the environment's randomness that no skill can control.

    A posterior that encodes s' (the incorrect model) has causal posterior p(z=k | a) = p(s_k | a),
    so its E-step KL is exactly this entropy.
    """
    p_action = [sum((p for (a, _), p in data.items() if a == b), ZERO) for b in range(len(ACTIONS))]
    return -sum(float(p) * _log(p / p_action[a]) for (a, _), p in data.items())


@dataclass(frozen=True)
class PlanningDecision:
    """The skill a model picks for reward, what it expects, and what executing it really earns.

    Attributes:
        skill: Index of the chosen skill (0 for z=1).
        believed: Expected reward under the model's own TAWM, sum_s' p(s' | z) r(s').
        true: Expected reward of running pi(a | z) in the real MDP.
    """

    skill: int
    believed: Fraction
    true: Fraction


def _expected_reward(next_state_dists: CondDist) -> Dist:
    """sum_s' row[s'] r(s') for each row of a table of next-state distributions."""
    return tuple(
        sum((p * r for p, r in zip(row, REWARD, strict=True)), ZERO) for row in next_state_dists
    )


ACTION_VALUES: Dist = _expected_reward(DYNAMICS)
"""True expected reward of a1, a2, a3: (10, -80, -100)."""


def believed_values(model: TabularSkillModel) -> Dist:
    """Expected reward of each skill as the model predicts it: sum_s' p(s' | z) r(s')."""
    return _expected_reward(model.tawm)


def true_values(model: TabularSkillModel) -> Dist:
    """Expected reward of running each skill in the MDP: sum_a pi(a | z) sum_s' P(s' | a) r(s')."""
    return tuple(
        sum((p * v for p, v in zip(row, ACTION_VALUES, strict=True)), ZERO) for row in model.policy
    )


def plan(model: TabularSkillModel) -> PlanningDecision:
    """One-step planning (§3, one skill): pick the skill whose TAWM predicts the most reward."""
    believed = believed_values(model)
    best = max(range(len(SKILLS)), key=lambda z: believed[z])
    return PlanningDecision(best, believed[best], true_values(model)[best])


@dataclass(frozen=True)
class ModelSummary:
    """Everything the appendix B comparison reports about one model (log-quantities in nats)."""

    model: TabularSkillModel
    log_likelihood: float
    elbo: float
    elbo_gap: float
    e_step_kl: float
    e_step_loss: float
    decision: PlanningDecision


def summarize(model: TabularSkillModel, data: Mapping[Transition, Fraction]) -> ModelSummary:
    """Evaluate one model on the data distribution."""
    return ModelSummary(
        model=model,
        log_likelihood=expected_log_likelihood(model, data),
        elbo=elbo(model, data),
        elbo_gap=elbo_gap(model, data),
        e_step_kl=e_step_kl(model, data),
        e_step_loss=e_step_loss(model, data),
        decision=plan(model),
    )


def _table(title: str, rows: list[str], columns: tuple[str, ...], cells: list[Dist]) -> list[str]:
    width = max(8, *(len(str(p)) + 2 for row in cells for p in row))
    lines = [f"  {title}", "    " + " " * 7 + "".join(f"{c:>{width}}" for c in columns)]
    lines += [
        f"    {r:<7}" + "".join(f"{str(p):>{width}}" for p in row)
        for r, row in zip(rows, cells, strict=True)
    ]
    return lines


def _model_section(summary: ModelSummary, data: Mapping[Transition, Fraction]) -> list[str]:
    m = summary.model
    transitions = sorted(data)
    lines = [f"{m.name} model"]
    lines += _table(
        "q(z|a,s')",
        [f"{ACTIONS[a]},{NEXT_STATES[s]}" for a, s in transitions],
        SKILLS,
        [m.posterior[t] for t in transitions],
    )
    lines += _table("pi(a|z)", list(SKILLS), ACTIONS, list(m.policy))
    lines += _table("p(s'|z)", list(SKILLS), NEXT_STATES, list(m.tawm))
    lines += _table("p(z)", [""], SKILLS, [m.prior])
    believed, true = believed_values(m), true_values(m)
    lines += _table(
        "expected reward per skill",
        ["model", "true"],
        SKILLS,
        [tuple(F(v) for v in believed), tuple(F(v) for v in true)],
    )
    d = summary.decision
    lines += [
        f"  ELBO (eq. 1)                   {summary.elbo:+.6f}",
        f"  log-likelihood - ELBO          {summary.elbo_gap:+.6f}",
        f"  E-step KL to eq. 14 posterior  {summary.e_step_kl:+.6f}",
        f"  E-step loss (eq. 15)           {summary.e_step_loss:+.6f}",
        f"  plans {SKILLS[d.skill]}: expects {d.believed}, really gets {d.true}",
    ]
    return lines


def format_report() -> str:
    """The appendix B comparison as readable text (what `oposm causal-example` prints)."""
    data = data_distribution()
    summaries = [summarize(m, data) for m in (correct_model(), incorrect_model())]
    lines = [
        "Appendix B: one-step MDP from s0: a1 -> s1 (+10); a2 -> s2 (+100) w.p. 1/10 or s3 (-100)",
        "w.p. 9/10; a3 -> s3 (-100).",
        "Data: uniformly random actions, p(a,s') = "
        + ", ".join(f"{ACTIONS[a]},{NEXT_STATES[s]}: {p}" for (a, s), p in sorted(data.items())),
        f"Data log-likelihood E log p(a,s') = {-_entropy(data):+.6f} nats; "
        f"environment noise H(s'|a) = {transition_noise_entropy(data):.6f} nats",
        "Corrected misprints:",
        *(
            f"  {k} printed ({', '.join(map(str, bad))}), used ({', '.join(map(str, good))})"
            for k, (bad, good) in PAPER_MISPRINTS.items()
        ),
        "",
    ]
    for s in summaries:
        lines += [*_model_section(s, data), ""]
    correct, incorrect = summaries
    lines += [
        f"Both ELBOs are {correct.elbo:+.6f} (they differ by "
        f"{abs(correct.elbo - incorrect.elbo):.1e}):",
        "  the ELBO cannot choose between the models.",
        f"The E-step KL is {correct.e_step_kl:.6f} for the correct model and "
        f"{incorrect.e_step_kl:.6f} = H(s'|a)",
        "  for the incorrect one: the E-step separates them.",
        f"Planning, the incorrect model picks {SKILLS[incorrect.decision.skill]} expecting "
        f"{incorrect.decision.believed} and gets {incorrect.decision.true};",
        f"  the correct model picks {SKILLS[correct.decision.skill]} and gets "
        f"{correct.decision.true}.",
    ]
    return "\n".join(lines)


def _entropy(dist: Mapping[Transition, Fraction]) -> float:
    return -sum(float(p) * _log(p) for p in dist.values() if p > 0)
