"""The residual TAWM (`train.tawm_residual`): its mean is s_0 plus the network's output, in the
likelihood, the planner's fused networks, the rollout and checkpoints; the paper's stays the
default and its checkpoints keep their bytes."""

import json

import torch
from factories import skill_model_config

from pipeline.model import SkillModel
from pipeline.model.checkpoint import load_model, save_model
from pipeline.model.rollout import rollout_skills
from pipeline.planning.fused import PlannerNets

SD, AD, Z = 4, 2, 3


def _model(residual: bool, components: int = 1, seed: int = 0) -> SkillModel:
    torch.manual_seed(seed)
    config = skill_model_config(
        SD, AD, z_dim=Z, hidden=16, tawm_components=components, tawm_residual=residual
    )
    return SkillModel(config)


def test_the_residual_mean_is_the_start_plus_the_papers_network_output():
    for components in (1, 3):
        paper, residual = _model(False, components), _model(True, components)
        residual.load_state_dict(paper.state_dict())  # the same weights
        s0, z, s_t = torch.randn(6, SD), torch.randn(6, Z), torch.randn(6, SD)
        mean, std = residual.tawm_outcome(s0, z)
        paper_mean, paper_std = paper.tawm_outcome(s0, z)
        torch.testing.assert_close(mean, paper_mean + s0, rtol=0, atol=0)
        assert torch.equal(std, paper_std)
        # The likelihood of s_T under the residual model is the paper's of s_T - s_0.
        torch.testing.assert_close(
            residual.tawm_dist(s0, z).log_prob(s_t),
            paper.tawm_dist(s0, z).log_prob(s_t - s0),
            rtol=1e-6,
            atol=1e-6,
        )


def test_the_planner_and_the_rollout_chain_the_residual_mean():
    for components in (1, 2):
        model = _model(True, components, seed=1)
        s0, z = torch.randn(8, SD), torch.randn(8, Z)
        mean = model.tawm_outcome(s0, z)[0]
        nets = PlannerNets(model)
        torch.testing.assert_close(nets.tawm_mean(s0, z), mean, rtol=1e-5, atol=1e-6)
        if components == 1:
            torch.testing.assert_close(nets.tawm_mean_std(s0, z)[0], mean, rtol=1e-5, atol=1e-6)
        chain = rollout_skills(model, s0, z=z[:, None])  # identity normalization: raw = normalized
        torch.testing.assert_close(chain.states[:, 1], mean, rtol=0, atol=0)


def test_a_residual_tawm_learns_to_leave_a_dim_it_cannot_predict_less_wrong():
    """s_T = s_0 in every dim (an object no skill touches): after the same few Adam steps the
    residual TAWM predicts the start within a fraction of the paper's error."""
    errors = {}
    for residual in (False, True):
        model = _model(residual, seed=2)
        opt = torch.optim.Adam(model.tawm.parameters(), lr=3e-3)
        gen = torch.Generator().manual_seed(0)
        for _ in range(100):
            s0, z = 2 * torch.randn(128, SD, generator=gen), torch.randn(128, Z, generator=gen)
            loss = -model.tawm_dist(s0, z).log_prob(s0).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        s0, z = 2 * torch.randn(500, SD, generator=gen), torch.randn(500, Z, generator=gen)
        with torch.no_grad():
            errors[residual] = (model.tawm_outcome(s0, z)[0] - s0).abs().mean().item()
    assert errors[True] < 0.5 * errors[False]


def test_the_papers_checkpoint_keeps_its_bytes_and_a_residual_one_round_trips(tmp_path):
    save_model(_model(False), tmp_path / "paper", {"window": 6})
    config = json.loads((tmp_path / "paper" / "config.json").read_text())
    assert "tawm_residual" not in json.dumps(config)  # as before the field existed
    assert load_model(tmp_path / "paper")[0].config.tawm_residual is False
    model = _model(True)
    save_model(model, tmp_path / "residual", {"window": 6})
    loaded, meta = load_model(tmp_path / "residual")
    assert meta["model"]["tawm_residual"] is True and loaded.config.tawm_residual
    s0, z = torch.randn(4, SD), torch.randn(4, Z)
    assert torch.equal(loaded.tawm_outcome(s0, z)[0], model.tawm_outcome(s0, z)[0])
