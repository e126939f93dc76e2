"""The mixture TAWM (`train.tawm_components > 1`): its likelihood, its readout, the planner's
fused networks, training on two-mode outcomes, and checkpoints."""

import math

import pytest
import torch
from factories import skill_model_config

from pipeline.model import SkillModel
from pipeline.model.checkpoint import load_model, save_model
from pipeline.model.rollout import rollout_skills
from pipeline.planning.fused import PlannerNets
from pipeline.training.data import WindowBatch
from pipeline.training.losses import m_step_loss, validation_metrics, vi_loss

SD, AD, Z = 4, 2, 3


def _model(components: int, seed: int = 0, **train) -> SkillModel:
    torch.manual_seed(seed)
    return SkillModel(
        skill_model_config(SD, AD, z_dim=Z, hidden=16, tawm_components=components, **train)
    )


def test_mixture_likelihood_is_the_log_sum_of_its_weighted_components():
    model = _model(3, tawm_shared_std=False)
    s0, z, s_t = torch.randn(5, SD), torch.randn(5, Z), torch.randn(5, SD)
    means, stds, logits = model.tawm(torch.cat([s0, z], -1))
    assert means.shape == stds.shape == (5, 3, SD) and logits.shape == (5, 3)
    by_hand = torch.logsumexp(
        torch.log_softmax(logits, -1)
        + torch.distributions.Normal(means, stds).log_prob(s_t[:, None]).sum(-1),
        dim=-1,
    )
    torch.testing.assert_close(model.tawm_dist(s0, z).log_prob(s_t), by_hand)


def test_shared_std_gives_one_std_per_component():
    model = _model(2, tawm_shared_std=True)
    _, stds, _ = model.tawm(torch.randn(6, SD + Z))
    assert torch.equal(stds, stds[..., :1].expand_as(stds))
    assert not torch.equal(stds[:, 0], stds[:, 1])  # each component has its own


def test_readout_is_the_most_probable_components_mean_and_the_planner_chains_it():
    model = _model(3)
    generator = torch.Generator().manual_seed(1)
    s0, z = torch.randn(64, SD, generator=generator), torch.randn(64, Z, generator=generator)
    with torch.no_grad():  # logits that vary across inputs more than at initialization, each
        last = model.tawm.std[2]  # centred over the rows, so that no component wins every row
        last.weight.normal_(0.0, 3.0, generator=generator)
        last.bias.zero_()
        last.bias[-3:] = -model.tawm(torch.cat([s0, z], -1))[2].mean(dim=0)
    means, stds, logits = model.tawm(torch.cat([s0, z], -1))
    best = logits.argmax(-1)
    assert len(best.unique()) > 1  # the rows pick different components
    mean, std = model.tawm_outcome(s0, z)
    torch.testing.assert_close(mean, means[torch.arange(64), best], rtol=0, atol=0)
    torch.testing.assert_close(std, stds[torch.arange(64), best], rtol=0, atol=0)
    nets = PlannerNets(model)
    torch.testing.assert_close(nets.tawm_mean(s0, z), mean, rtol=1e-5, atol=1e-6)
    # The rollout chains the readout in raw units (here the identity normalization).
    chain = rollout_skills(model, s0, z=z[:, None])
    torch.testing.assert_close(chain.states[:, 1], mean, rtol=0, atol=0)


def test_a_one_component_model_keeps_the_papers_tawm():
    model = _model(1)
    s0, z = torch.randn(5, SD), torch.randn(5, Z)
    assert isinstance(model.tawm_dist(s0, z), torch.distributions.Independent)
    direct = model.tawm(torch.cat([s0, z], -1))
    for ours, theirs in zip(model.tawm_outcome(s0, z), direct, strict=True):
        assert torch.equal(ours, theirs)


def test_a_mixture_learns_both_outcomes_of_a_skill_where_a_gaussian_predicts_neither():
    """s_T = s_0 + 1 or s_0 - 1 with equal odds, whatever z: a cube carried or dropped."""
    fitted = {}
    for k in (1, 2):
        model = _model(k, seed=1, tawm_shared_std=False)
        opt = torch.optim.Adam(model.tawm.parameters(), lr=1e-2)
        gen = torch.Generator().manual_seed(0)
        for _ in range(400):
            s0, z = torch.randn(256, SD, generator=gen), torch.randn(256, Z, generator=gen)
            sign = torch.randint(0, 2, (256, 1), generator=gen) * 2.0 - 1.0
            s_t = s0 + sign + 0.05 * torch.randn(256, SD, generator=gen)
            loss = -model.tawm_dist(s0, z).log_prob(s_t).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        s0, z = torch.zeros(200, SD), torch.randn(200, Z, generator=gen)
        fitted[k] = (loss.item(), model, s0, z)
    nll_gauss, nll_mix = fitted[1][0], fitted[2][0]
    assert nll_mix < nll_gauss - 2.0  # the two-mode data are far likelier under the mixture
    _, model, s0, z = fitted[2]
    means, _, logits = model.tawm(torch.cat([s0, z], -1))
    weights = logits.softmax(-1).mean(0)
    assert weights.min() > 0.3  # both modes kept
    modes = means.mean(0).mean(-1).sort().values  # the two components' mean shift
    torch.testing.assert_close(modes, torch.tensor([-1.0, 1.0]), atol=0.15, rtol=0)
    gauss_model, s0, z = fitted[1][1], fitted[1][2], fitted[1][3]
    gauss_shift = gauss_model.tawm_outcome(s0, z)[0].mean()
    assert abs(gauss_shift) < 0.3  # the Gaussian's mean lies between the outcomes
    assert model.tawm_outcome(s0, z)[0].abs().mean() > 0.8  # the readout is an outcome


def test_em_and_vi_losses_train_a_mixture_tawm():
    model = _model(2)
    batch = WindowBatch(torch.randn(8, 6, SD), torch.randn(8, 5, AD))
    loss, terms = m_step_loss(model, batch)
    loss.backward()
    assert math.isfinite(loss.item()) and math.isfinite(terms["st_nll"].item())
    grads = [p.grad for p in model.tawm.parameters()]
    assert all(g is not None and g.abs().sum() > 0 for g in grads)
    assert math.isfinite(vi_loss(model, batch)[0].item())
    metrics = validation_metrics(model, batch, prior_eps=torch.randn(4, Z))
    assert all(torch.isfinite(v).all() for v in metrics.values())


def test_a_mixture_checkpoint_round_trips(tmp_path):
    model = _model(3)
    save_model(model, tmp_path / "ckpt", {"window": 6})
    loaded, meta = load_model(tmp_path / "ckpt")
    assert meta["model"]["tawm_components"] == 3
    assert loaded.config.tawm_components == 3
    x = torch.randn(4, SD + Z)
    for ours, theirs in zip(loaded.tawm(x), model.tawm(x), strict=True):
        assert torch.equal(ours, theirs)


def test_a_mixture_needs_two_components():
    from pipeline.model.networks import MixtureGaussianMLP

    with pytest.raises(ValueError, match="at least 2 components"):
        MixtureGaussianMLP(4, 8, 4, components=1)


def test_sampled_outcomes_draw_components_by_their_weights():
    model = _model(2)
    with torch.no_grad():  # weights 0.8 / 0.2 everywhere, the two means far apart
        model.tawm.std[2].weight.zero_()
        model.tawm.std[2].bias[-2:] = torch.tensor([math.log(0.8), math.log(0.2)])
        model.tawm.mean[2].weight.zero_()
        model.tawm.mean[2].bias.copy_(torch.tensor([5.0] * SD + [-5.0] * SD))
    s0, z = torch.randn(4000, SD), torch.randn(4000, Z)
    gen = torch.Generator().manual_seed(3)
    mean, _ = model.tawm_outcome(s0, z, gen)
    share = (mean[:, 0] > 0).float().mean().item()
    assert abs(share - 0.8) < 0.03
    torch.testing.assert_close(model.tawm_outcome(s0, z)[0], torch.full((4000, SD), 5.0))
    # The particles of the open loop follow the drawn components: both modes appear.
    chain = rollout_skills(model, s0[:200], z=z[:200, None], generator=gen)
    assert (chain.states[:, 1, 0] > 0).any() and (chain.states[:, 1, 0] < 0).any()


def test_a_single_gaussian_samples_without_an_extra_draw():
    model = _model(1)
    s0, z = torch.randn(8, SD), torch.randn(8, Z)
    a, b = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    model.tawm_outcome(s0, z, a)
    assert torch.equal(torch.rand(3, generator=a), torch.rand(3, generator=b))
