import numpy as np
import pytest
from factories import make_episodes, make_info

from pipeline.errors import UserError
from pipeline.segments import SPLITS, build_segments, load_segments, save_segments

FRACTIONS = {"train": 0.6, "validation": 0.2, "test": 0.2}


def _segments(info, lengths=(50, 80, 45, 60, 70, 90, 55, 65, 75, 100), window=10, stride=1):
    return build_segments(make_episodes(list(lengths)), info, window, stride, FRACTIONS, seed=3)


def test_windows_never_cross_an_episode_boundary(info):
    seg = _segments(info)
    for split in SPLITS:
        states, actions = seg.windows(split)
        assert states.shape[1:] == (10, 4) and actions.shape[1:] == (9, 2)
        # state[:, 0] is the episode index, state[:, 1] the step: one episode, consecutive steps.
        assert np.all(states[:, :, 0] == states[:, :1, 0])
        assert np.all(np.diff(states[:, :, 1], axis=1) == 1)


def test_every_window_of_every_episode_is_indexed(info):
    lengths = (50, 80, 45, 60, 70, 90, 55, 65, 75, 100)
    seg = _segments(info, lengths, window=10, stride=3)
    total = sum(len(range(0, n - 10 + 1, 3)) for n in lengths)
    assert sum(seg.starts[s].size for s in SPLITS) == total


def test_no_episode_is_in_two_splits(info):
    seg = _segments(info)
    owners = {}
    for split in SPLITS:
        states, _ = seg.windows(split)
        for ep in np.unique(states[:, 0, 0]):
            assert owners.setdefault(int(ep), split) == split
    assert set(owners.values()) == set(SPLITS)
    assert sorted(owners) == list(range(10))


def test_split_sizes_follow_the_fractions(info):
    summary = _segments(info).summary()
    assert [summary[s]["episodes"] for s in SPLITS] == [6, 2, 2]


def test_normalization_uses_train_only(info):
    seg = _segments(info)
    train_episodes = seg.episodes_in("train")
    rows = np.concatenate(
        [np.arange(seg.episode_offsets[e], seg.episode_offsets[e + 1]) for e in train_episodes]
    )
    np.testing.assert_allclose(
        seg.stats.state_mean, seg.states[rows].mean(0, dtype=np.float64), rtol=1e-9
    )
    np.testing.assert_allclose(
        seg.stats.action_std, seg.actions[rows].std(0, dtype=np.float64), rtol=1e-9
    )
    # Column 0 is the episode index: its train mean differs from the all-episode mean.
    assert seg.stats.state_mean[0] != pytest.approx(seg.states[:, 0].mean())


def test_constant_dimension_gets_a_floor_not_a_zero_std(info):
    eps = make_episodes([30, 30, 30])
    for ep in eps:
        ep.observations[:, 3] = 1.0
    seg = build_segments(eps, info, 10, 1, {"train": 1.0, "validation": 0.0, "test": 0.0})
    assert seg.stats.state_std[3] > 0


def test_same_seed_same_split_and_different_seed_different(info):
    eps = make_episodes([40] * 20)
    a = build_segments(eps, info, 10, 1, FRACTIONS, seed=1)
    b = build_segments(eps, info, 10, 1, FRACTIONS, seed=1)
    c = build_segments(eps, info, 10, 1, FRACTIONS, seed=2)
    np.testing.assert_array_equal(a.episode_split, b.episode_split)
    assert not np.array_equal(a.episode_split, c.episode_split)


def test_short_episodes_are_dropped_and_all_short_is_an_error(info):
    seg = build_segments(make_episodes([5, 50, 50, 50, 8]), info, 10, 1, FRACTIONS)
    assert seg.episode_index.tolist() == [1, 2, 3]
    with pytest.raises(UserError, match="shorter than the window"):
        build_segments(make_episodes([5, 6]), info, 10, 1, FRACTIONS)


def test_no_episodes_is_an_error(info):
    with pytest.raises(UserError, match="no episodes"):
        build_segments([], info, 10, 1, FRACTIONS)


def test_too_few_episodes_for_the_splits_is_an_error(info):
    with pytest.raises(UserError, match="too few"):
        build_segments(make_episodes([50, 50]), info, 10, 1, FRACTIONS)


def test_save_load_round_trip(tmp_path, info):
    seg = _segments(info)
    save_segments(seg, tmp_path / "seg")
    back = load_segments(tmp_path / "seg")
    assert back.info == seg.info and back.window == seg.window
    for name in ("states", "actions", "physics", "episode_offsets", "episode_split"):
        np.testing.assert_array_equal(getattr(back, name), getattr(seg, name))
    for split in SPLITS:
        np.testing.assert_array_equal(back.starts[split], seg.starts[split])
    np.testing.assert_array_equal(back.stats.state_std, seg.stats.state_std)
    assert [p.name for p in tmp_path.iterdir()] == ["seg"]  # no temp directories left


def test_save_replaces_an_existing_directory_whole(tmp_path, info):
    save_segments(_segments(info, window=10), tmp_path / "seg")
    save_segments(_segments(info, window=20), tmp_path / "seg")
    assert load_segments(tmp_path / "seg").window == 20


def test_load_missing_or_corrupt_segments_is_a_user_error(tmp_path, info):
    with pytest.raises(UserError, match="run `oposm segment`"):
        load_segments(tmp_path / "nothing")
    save_segments(_segments(info), tmp_path / "seg")
    (tmp_path / "seg" / "segments.safetensors").write_bytes(b"garbage")
    with pytest.raises(UserError, match="unreadable"):
        load_segments(tmp_path / "seg")


def _edit_meta(directory, edit):
    import json

    path = directory / "segments.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda m: m.pop("window"), "segments.json has no 'window' entry"),
        (lambda m: m.pop("stats"), "segments.json has no 'stats' entry"),
        (lambda m: m.update(window="forty"), "bad value for 'window'"),
        (lambda m: m["dataset"].update(colour="red"), "unknown key 'dataset.colour'"),
        (lambda m: m["dataset"].update(state_names=["x", "y", "vx"]), "states have shape"),
        (lambda m: m["stats"].update(action_std=[1.0]), "action stats have shape"),
        (lambda m: m.update(window=10_000), "windows of 10000 states run past"),
    ],
    ids=["no window", "no stats", "bad window", "unknown info key", "state dim", "stats", "long"],
)
def test_segments_json_missing_an_entry_or_mismatched_is_a_user_error(
    tmp_path, info, edit, message
):
    save_segments(_segments(info), tmp_path / "seg")
    _edit_meta(tmp_path / "seg", edit)
    with pytest.raises(UserError, match=message) as caught:
        load_segments(tmp_path / "seg")
    text = str(caught.value)
    assert str(tmp_path / "seg") in text and "re-run `oposm segment`" in text
    assert "\n" not in text


def test_segments_json_that_is_not_an_object_is_a_user_error(tmp_path, info):
    save_segments(_segments(info), tmp_path / "seg")
    (tmp_path / "seg" / "segments.json").write_text("[1, 2]")
    with pytest.raises(UserError, match="not a JSON object"):
        load_segments(tmp_path / "seg")


def test_exclude_leaves_out_every_window_holding_an_excluded_step():
    episodes = make_episodes([30, 25, 30, 28, 30, 26], seed=3)

    def bad(states: np.ndarray) -> np.ndarray:  # state[:, 1] is the step within the episode
        return (states[:, 1] + states[:, 0]) % 13 == 7

    split = {"train": 0.5, "validation": 0.25, "test": 0.25}
    full = build_segments(episodes, make_info(), window=5, split_fractions=split, seed=0)
    kept = build_segments(episodes, make_info(), 5, split_fractions=split, seed=0, exclude=bad)
    for name in SPLITS:
        s = full.starts[name]
        clean = np.array([not bad(full.states[t : t + 5]).any() for t in s], dtype=bool)
        assert not clean.all()
        np.testing.assert_array_equal(kept.starts[name], s[clean])
    np.testing.assert_array_equal(kept.states, full.states)  # the data stay; only windows go
