"""A TAWM trained to chain K skills (`train.tawm_chain`): windows followed by K - 1 more of the
same episode, the chained likelihood against a hand computation, one window as eq. 16 exactly,
and the train stage end to end."""

import hashlib
import json

import numpy as np
import pytest
import torch
from factories import make_info, make_skill_episodes, skill_model_config, train_updater

from pipeline import cpu_math
from pipeline.config import Params
from pipeline.errors import UserError
from pipeline.model import SkillModel
from pipeline.paths import Paths
from pipeline.segments import build_segments, save_segments
from pipeline.training.data import WindowSampler, chained_starts
from pipeline.training.losses import chained_tawm_log_prob, m_step_loss, policy_log_prob

SPLIT = {"train": 0.8, "validation": 0.1, "test": 0.1}


@pytest.fixture(scope="module")
def segments():
    episodes = make_skill_episodes(n_episodes=12, length=60, seed=0)
    return build_segments(episodes, make_info("skills", physics_dim=0), 11, 1, SPLIT, seed=0)


def _model(segments) -> SkillModel:
    torch.manual_seed(0)
    model = SkillModel(skill_model_config(4, 2, z_dim=4, hidden=16))
    s = segments.stats
    model.set_normalization(s.state_mean, s.state_std, s.action_mean, s.action_std)
    return model


def test_a_chained_start_is_followed_by_its_windows_in_the_same_episode(segments):
    t, starts = segments.horizon, segments.starts["train"]
    episode = np.searchsorted(segments.episode_offsets, starts, side="right")
    for chain in (2, 3):
        kept = chained_starts(segments, "train", chain)
        want = [
            s for s, e in zip(starts, episode, strict=True)
            if s + chain * t < segments.episode_offsets[e]  # the last state inside episode e
        ]  # fmt: skip
        assert kept.tolist() == want
    assert len(chained_starts(segments, "train", 3)) < len(chained_starts(segments, "train", 2))
    with pytest.raises(UserError, match="train.tawm_chain=7"):
        chained_starts(segments, "train", 7)  # 7 windows of 10 steps: longer than 60 steps


def test_the_sampler_gives_each_window_and_the_ones_after_it_end_to_end(segments):
    sampler = WindowSampler(segments, "train", torch.device("cpu"), 0, chain=3)
    batch = sampler.sample(8)
    t = segments.horizon
    assert batch.states.shape == (8, t + 1, 4) and batch.actions.shape == (8, t, 2)
    assert batch.after_states.shape == (8, 2 * t, 4) and batch.after_actions.shape == (8, 2 * t, 2)
    plain = WindowSampler(segments, "train", torch.device("cpu"), 0)
    stats = segments.stats
    for row in range(8):
        # the normalized steps from the window's first state on, in the episode's order
        first = int(torch.nonzero((plain.states == batch.states[row, 0]).all(-1))[0])
        states = (segments.states[first : first + 3 * t + 1] - stats.state_mean) / stats.state_std
        actions = (segments.actions[first : first + 3 * t] - stats.action_mean) / stats.action_std
        got_s = torch.cat([batch.states[row], batch.after_states[row]])
        got_a = torch.cat([batch.actions[row], batch.after_actions[row]])
        torch.testing.assert_close(got_s, torch.as_tensor(states, dtype=torch.float32))
        torch.testing.assert_close(got_a, torch.as_tensor(actions, dtype=torch.float32))
    # one window: the batch of before, no windows after
    assert plain.sample(8).after_states is None


def test_the_chained_likelihood_feeds_the_tawm_its_own_prediction(segments):
    model = _model(segments)
    g = torch.Generator().manual_seed(1)
    s0, z = torch.randn(5, 4, generator=g), torch.randn(5, 3, 4, generator=g)
    outcomes = torch.randn(5, 3, 4, generator=g)
    got = chained_tawm_log_prob(model, s0, z, outcomes)
    start, want = s0, []
    for k in range(3):
        mean, std = model.tawm(torch.cat([start, z[:, k]], -1))
        want.append(torch.distributions.Normal(mean, std).log_prob(outcomes[:, k]).sum(-1))
        start = mean
    torch.testing.assert_close(got, torch.stack(want, 1))
    # the second outcome's likelihood reaches the TAWM through the first prediction too
    s0.requires_grad_(True)
    chained_tawm_log_prob(model, s0, z, outcomes)[:, 1].sum().backward()
    assert s0.grad.abs().sum() > 0


def test_the_m_step_over_chained_windows_averages_the_tawm_over_the_skills(segments):
    model = _model(segments)
    batch = WindowSampler(segments, "train", torch.device("cpu"), 0, chain=2).sample(16)
    torch.manual_seed(3)
    loss, metrics = m_step_loss(model, batch)
    torch.manual_seed(3)  # the same posterior draws, by hand
    t = batch.actions.shape[1]
    states = torch.cat([batch.states, batch.after_states], 1)
    actions = torch.cat([batch.actions, batch.after_actions], 1)
    windows, acts = states[:, : 2 * t].reshape(32, t, 4), actions.reshape(32, t, 2)
    with torch.no_grad():
        z = model.posterior_dist(windows, acts).rsample().reshape(16, 2, -1)
    s0 = batch.states[:, 0]
    first = model.tawm_dist(s0, z[:, 0]).log_prob(states[:, t])
    start = model.tawm_outcome(s0, z[:, 0])[0]
    second = model.tawm_dist(start, z[:, 1]).log_prob(states[:, 2 * t])
    log_pi = policy_log_prob(model, batch, z[:, 0])
    log_prior = model.prior_dist(s0).log_prob(z[:, 0])
    want = -(log_pi + (first + second) / 2 + log_prior).mean()
    torch.testing.assert_close(loss, want)
    torch.testing.assert_close(metrics["st_nll_chained"], -second.mean())
    torch.testing.assert_close(metrics["st_nll"], -first.mean())


def test_em_with_a_chained_tawm_updates_and_stays_finite(segments):
    model = _model(segments)
    updater = train_updater(model, lr_e=1e-3, lr_m=1e-3)
    sampler = WindowSampler(segments, "train", torch.device("cpu"), 0, chain=2)
    before = [p.detach().clone() for p in model.tawm.parameters()]
    for _ in range(3):
        metrics = updater.step(sampler.sample(16))
    assert all(torch.isfinite(v).all() for v in metrics.values())
    assert "st_nll_chained" in metrics
    assert any(not torch.equal(b, p) for b, p in zip(before, model.tawm.parameters(), strict=True))


def _stage_params(**train) -> Params:
    small = {"z_dim": 4, "hidden": 16, "batch_size": 8, "val_windows": 20, "device": "cpu"}
    steps = {"max_steps": 6, "eval_every": 3, "checkpoint_every": 3}
    return Params.model_validate({"ingest": {"name": "skills"}, "train": small | steps | train})


def test_the_train_stage_runs_a_chained_tawm_and_one_skill_keeps_its_resume_key(tmp_path, segments):
    from stages import train

    save_segments(segments, tmp_path / "data" / "segments" / "skills")
    paths = Paths(tmp_path / "data")
    with torch.random.fork_rng():
        progress = train.run(_stage_params(tawm_chain=2), paths, progress_bar=False)
    assert progress.step == 6
    segments_dir = paths.segments("skills")
    one = train._fingerprint(_stage_params().train, segments_dir, 1)
    two = train._fingerprint(_stage_params(tawm_chain=2).train, segments_dir, 1)
    residual = train._fingerprint(_stage_params(tawm_residual=True).train, segments_dir, 1)
    assert one != two and one != residual
    # at their defaults (1, false) the keys are left out: a state saved before they existed
    before = {
        "state_format": 2,
        "train": _stage_params().train.model_dump(
            exclude=train._BUDGET_KEYS | {"tawm_chain", "tawm_residual"}
        ),
        "segments": json.loads((segments_dir / "segments.json").read_text()),
        "processes": 1,
        "cpu_math": cpu_math.mode(),
    }
    assert one == hashlib.sha256(json.dumps(before, sort_keys=True).encode()).hexdigest()
