"""The skill model's networks, losses and checkpoints, on tiny tensors."""

import math

import pytest
import torch
from factories import skill_model_config
from torch import nn

from pipeline.errors import UserError
from pipeline.model import SkillModel, load_model, save_model
from pipeline.training.data import WindowBatch
from pipeline.training.losses import e_objective, m_objective, policy_log_prob, vi_objective

CONFIG = skill_model_config(state_dim=2, action_dim=1, z_dim=2, hidden=3, tawm_shared_std=True)


def _normal_log_pdf(x: float, mean: float, std: float) -> float:
    return -0.5 * ((x - mean) / std) ** 2 - math.log(std) - 0.5 * math.log(2 * math.pi)


def _constant_model(policy_mean=0.5, prior_mean=0.0, tawm_mean=1.0, q_mean=0.2) -> SkillModel:
    """All weights zero: every head outputs its last bias, so every density is hand-computable.
    Every std is softplus(0) + min_std = log 2 + 1e-4."""
    model = SkillModel(CONFIG)
    for module in model.modules():
        if isinstance(module, nn.Linear):
            nn.init.zeros_(module.weight)
            nn.init.zeros_(module.bias)
    model.policy.head.mean[-1].bias.data.fill_(policy_mean)
    model.prior.head.mean[-1].bias.data.fill_(prior_mean)
    model.tawm.head.mean[-1].bias.data.fill_(tawm_mean)
    model.posterior.head.mean[-1].bias.data.fill_(q_mean)
    return model


STD = math.log(2) + 1e-4
# B = 2 windows of T = 2 actions (3 states) with 2-d states and 1-d actions.
BATCH = WindowBatch(
    states=torch.tensor(
        [[[0.0, 0.0], [0.1, 0.2], [1.0, 2.0]], [[1.0, 1.0], [0.0, 0.0], [3.0, -1.0]]]
    ),
    actions=torch.tensor([[[0.5], [1.5]], [[-0.5], [0.0]]]),
)
Z = torch.tensor([[0.1, -0.3], [0.4, 0.0]])


def test_policy_log_prob_sums_over_steps_by_hand():
    model = _constant_model(policy_mean=0.5)
    got = policy_log_prob(model, BATCH, Z)
    want = [
        sum(_normal_log_pdf(a, 0.5, STD) for a in (0.5, 1.5)),
        sum(_normal_log_pdf(a, 0.5, STD) for a in (-0.5, 0.0)),
    ]
    torch.testing.assert_close(got, torch.tensor(want), rtol=1e-5, atol=1e-5)


def test_e_objective_by_hand():
    model = _constant_model(policy_mean=0.5, prior_mean=0.0, q_mean=0.2)
    q = model.posterior_dist(BATCH.states[:, :-1], BATCH.actions)
    got = e_objective(model, BATCH, q, Z)
    per_window = []
    for b, actions in enumerate([(0.5, 1.5), (-0.5, 0.0)]):
        log_pi = sum(_normal_log_pdf(a, 0.5, STD) for a in actions)
        log_prior = sum(_normal_log_pdf(float(z), 0.0, STD) for z in Z[b])
        log_q = sum(_normal_log_pdf(float(z), 0.2, STD) for z in Z[b])
        per_window.append(log_pi + log_prior - log_q)
    assert float(got.detach()) == pytest.approx(-sum(per_window) / 2, rel=1e-5)


def test_m_objective_by_hand_includes_the_world_model_of_the_last_state():
    model = _constant_model(policy_mean=0.5, prior_mean=0.0, tawm_mean=1.0)
    got, terms = m_objective(model, BATCH, Z)
    log_tawm = [sum(_normal_log_pdf(x, 1.0, STD) for x in s_t) for s_t in ((1.0, 2.0), (3.0, -1.0))]
    torch.testing.assert_close(terms["log_tawm"], torch.tensor(log_tawm), rtol=1e-5, atol=1e-5)
    per_window = []
    for b, actions in enumerate([(0.5, 1.5), (-0.5, 0.0)]):
        log_pi = sum(_normal_log_pdf(a, 0.5, STD) for a in actions)
        log_prior = sum(_normal_log_pdf(float(z), 0.0, STD) for z in Z[b])
        per_window.append(log_pi + log_tawm[b] + log_prior)
    assert float(got.detach()) == pytest.approx(-sum(per_window) / 2, rel=1e-5)


def test_vi_objective_kl_matches_the_closed_form():
    model = _constant_model(prior_mean=0.0, q_mean=0.2)
    q = model.posterior_dist(BATCH.states[:, :-1], BATCH.actions)
    _, terms = vi_objective(model, BATCH, q, Z)
    # KL(N(0.2, s) || N(0, s)) per dim = 0.2^2 / (2 s^2), two dims.
    torch.testing.assert_close(terms["kl"], torch.full((2,), 2 * 0.04 / (2 * STD**2)))


def test_shared_tawm_std_is_one_scalar_per_prediction():
    model = SkillModel(CONFIG)
    _, std = model.tawm(torch.randn(5, CONFIG.state_dim + CONFIG.z_dim))
    assert std.shape == (5, 2) and torch.all(std[:, 0] == std[:, 1])
    per_dim = SkillModel(skill_model_config(2, 1, z_dim=2, hidden=3, tawm_shared_std=False))
    _, std = per_dim.tawm(torch.randn(5, 4))
    assert not torch.all(std[:, 0] == std[:, 1])


def test_raw_interface_undoes_the_normalization():
    model = _constant_model(tawm_mean=1.0)
    model.set_normalization([10.0, -5.0], [2.0, 4.0], [0.0], [3.0])
    mean, std = model.predict_end(torch.zeros(1, 2), torch.zeros(1, 2))
    torch.testing.assert_close(mean, torch.tensor([[12.0, -1.0]]))
    torch.testing.assert_close(std, torch.tensor([[2 * STD, 4 * STD]]))


def test_checkpoint_round_trip_is_bit_exact(tmp_path):
    torch.manual_seed(0)
    model = SkillModel(CONFIG)
    model.set_normalization([1.0, 2.0], [3.0, 4.0], [0.5], [0.25])
    save_model(model, tmp_path, {"dataset": {"name": "x"}})
    back, meta = load_model(tmp_path, expected=CONFIG)
    assert meta["dataset"] == {"name": "x"}
    for (name, a), (_, b) in zip(
        model.state_dict().items(), back.state_dict().items(), strict=True
    ):
        assert torch.equal(a, b), name
    s, z = torch.randn(4, 2), torch.randn(4, 2)
    assert torch.equal(model.predict_end(s, z)[0], back.predict_end(s, z)[0])


def test_checkpoint_from_another_config_names_the_differing_fields(tmp_path):
    save_model(SkillModel(CONFIG), tmp_path, {})
    other = skill_model_config(state_dim=2, action_dim=1, z_dim=8, hidden=3, tawm_shared_std=False)
    with pytest.raises(UserError, match=r"z_dim: 2 != 8.*tawm_shared_std: True != False"):
        load_model(tmp_path, expected=other)


def test_missing_or_corrupt_checkpoint_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="run `oposm train`"):
        load_model(tmp_path)
    save_model(SkillModel(CONFIG), tmp_path, {})
    (tmp_path / "model.safetensors").write_bytes(b"\0" * 10)
    with pytest.raises(UserError, match="unreadable"):
        load_model(tmp_path)


CENSORED = skill_model_config(2, 1, z_dim=2, hidden=3, action_low=(-1.0,), action_high=(1.0,))


def _normal_log_sf(x: float, mean: float, std: float) -> float:
    """log P(X >= x) for X ~ N(mean, std^2), from math.erfc."""
    return math.log(0.5 * math.erfc((x - mean) / (std * math.sqrt(2))))


def test_censored_policy_scores_clipped_actions_as_the_mass_beyond_the_bound():
    """train.action_likelihood censored: an action at a bound scores log P(beyond it), one
    inside the Gaussian density; raw bounds are normalized with the action statistics."""
    model = SkillModel(CENSORED)
    for module in model.modules():
        if isinstance(module, nn.Linear):
            nn.init.zeros_(module.weight)
            nn.init.zeros_(module.bias)
    model.policy.head.mean[-1].bias.data.fill_(0.3)
    model.set_normalization([0.0, 0.0], [1.0, 1.0], [0.5], [2.0])  # bounds: -0.75, 0.25
    s, z = torch.zeros(3, 2), torch.zeros(3, 2)
    a_n = model.norm_actions(torch.tensor([[1.0], [-1.0], [0.0]]))
    got = model.policy_log_prob(s, z, a_n)
    want = [
        _normal_log_sf(0.25, 0.3, STD),  # at the upper bound: P(X >= 0.25)
        _normal_log_sf(0.75, -0.3, STD),  # at the lower: P(X <= -0.75) = P(-X >= 0.75)
        _normal_log_pdf(-0.25, 0.3, STD),  # inside
    ]
    torch.testing.assert_close(got, torch.tensor(want), rtol=1e-5, atol=1e-5)


def test_censored_likelihood_of_a_clipped_action_is_bounded_as_the_std_vanishes():
    """The Gaussian density of a clipped action grows without limit as the std shrinks (what
    drove EM's collapse); the censored likelihood is at most 0 (probability 1)."""
    from pipeline.model.skill_model import censored_log_prob

    low, high, x = torch.tensor(-1.0), torch.tensor(1.0), torch.tensor(1.0)
    for std in (1.0, 1e-2, 1e-4):
        mean, s = torch.tensor(1.0 - std), torch.tensor(std)
        density = torch.distributions.Normal(mean, s).log_prob(x)
        censored = censored_log_prob(mean, s, x, low, high)
        assert censored <= 0.0
        assert density > censored  # here the density rewards the small std...
    assert density > 7.5  # ...without limit: 7.8 nats at std 1e-4


def test_censored_config_round_trips_and_clips_actions(tmp_path):
    model = SkillModel(CENSORED)
    model.set_normalization([0.0, 0.0], [1.0, 1.0], [0.0], [1.0])
    save_model(model, tmp_path, {})
    loaded, meta = load_model(tmp_path, expected=CENSORED)
    assert loaded.config == CENSORED and meta["model"]["action_high"] == [1.0]
    assert "action_low" not in dict(loaded.state_dict())  # from the config, not the weights
    torch.manual_seed(0)
    acts = loaded.act(torch.zeros(500, 2), torch.zeros(500, 2) + 5.0, sample=True)
    assert acts.min() >= -1.0 and acts.max() <= 1.0
    assert SkillModel(CONFIG).clip_actions(torch.tensor([3.0])).item() == 3.0  # no bounds


def test_censored_config_checks_its_bounds():
    with pytest.raises(ValueError, match="both or neither"):
        skill_model_config(2, 1, action_low=(-1.0,))
    with pytest.raises(ValueError, match="2 values for 1 dims"):
        skill_model_config(2, 1, action_low=(-1.0, -1.0), action_high=(1.0, 1.0))


def test_policy_ignore_dims_hides_those_dims_from_the_policy_only(tmp_path):
    config = skill_model_config(
        state_dim=4,
        action_dim=2,
        z_dim=3,
        hidden=8,
        tawm_shared_std=True,
        policy_ignore_dims=[2, 1],
    )
    assert config.policy_ignore_dims == (1, 2)
    torch.manual_seed(0)
    model = SkillModel(config)
    model.set_normalization([1.0, 2.0, 3.0, 4.0], [2.0, 1.0, 0.5, 3.0], [0.1, -0.2], [0.5, 2.0])
    s, z = torch.randn(5, 4), torch.randn(5, 3)
    moved = s.clone()
    moved[:, 1:3] += 10.0 * torch.randn(5, 2)  # only the ignored dims change
    assert torch.equal(model.act(s, z), model.act(moved, z))
    moved[:, 3] += 1.0  # a seen dim changes the action
    assert not torch.allclose(model.act(s, z), model.act(moved, z))
    # the TAWM still sees every dim
    assert not torch.allclose(model.predict_end(s, z)[0], model.predict_end(moved, z)[0])
    save_model(model, tmp_path, {})
    back, _ = load_model(tmp_path, expected=config)
    assert back.config.policy_ignore_dims == (1, 2)
    assert torch.equal(back.act(s, z), model.act(s, z))


@pytest.mark.parametrize("dims", [[4], [-1], [0, 1, 2, 3]])
def test_policy_ignore_dims_must_leave_the_policy_some_state(dims):
    with pytest.raises(ValueError, match="policy_ignore_dims"):
        skill_model_config(
            state_dim=4,
            action_dim=2,
            z_dim=3,
            hidden=8,
            tawm_shared_std=True,
            policy_ignore_dims=dims,
        )
