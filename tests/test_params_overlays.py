"""Params variants are overlays: `extends: <base>` and only the keys that differ from the base,
deep-merged onto it by the one loader that `load_params`, `-p/--params` and
`load_expert_params` share (`pipeline.config.read_params_file`)."""

from pathlib import Path

import pytest
import yaml
from factories import one_line_error

from pipeline.ant_expert.config import AntExpertParams, load_expert_params
from pipeline.config import EXTENDS, load_params, params_files, read_params_file

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = sorted(p.name for p in ROOT.glob("params-*.yaml"))
MAX_LINES = 60


def _leaves(raw: dict, prefix: tuple = ()):
    """(key path, value) of every non-mapping value."""
    for key, value in raw.items():
        if isinstance(value, dict):
            yield from _leaves(value, (*prefix, key))
        else:
            yield (*prefix, key), value


def _write(directory: Path, name: str, text: str) -> Path:
    path = directory / name
    path.write_text(text)
    return path


def test_the_repository_has_the_known_variants():
    mazes = [f"pointmaze-{m}" for m in ("medium", "large", "giant", "teleport")]
    mazes += ["antmaze-medium", "antmaze-large"]
    assert {"params-paper.yaml", *(f"params-ogbench-{m}.yaml" for m in mazes)} <= set(VARIANTS)


def test_params_yaml_is_a_plain_file():
    """DVC reads params.yaml itself: it stays a full file, not an overlay."""
    assert EXTENDS not in yaml.safe_load((ROOT / "params.yaml").read_text())
    assert params_files(ROOT / "params.yaml") == [ROOT / "params.yaml"]


@pytest.mark.parametrize("name", VARIANTS)
def test_variant_is_a_short_overlay_that_resolves(name):
    path = ROOT / name
    text = path.read_text()
    assert len(text.splitlines()) <= MAX_LINES, f"{name}: over {MAX_LINES} lines"
    raw = yaml.safe_load(text)
    assert next(iter(raw)) == EXTENDS, f"{name}: `extends:` must be its first key"
    load_params(path)  # validates
    chain = params_files(path)
    assert chain[0] == path and chain[-1] == ROOT / "params.yaml"


@pytest.mark.parametrize("name", VARIANTS)
def test_variant_holds_only_what_differs_from_its_base(name):
    path = ROOT / name
    raw = yaml.safe_load(path.read_text())
    base = load_params(path.parent / raw.pop(EXTENDS)).model_dump(mode="json")
    for key, value in _leaves(raw):
        node = base
        for part in key:
            node = node[part]  # a KeyError here: not a params key (validation says so too)
        assert value != node, f"{name}: {'.'.join(key)}: {value!r} repeats its base's value"


def test_overlay_deep_merges_mappings_and_replaces_lists_and_scalars(tmp_path):
    _write(tmp_path, "base.yaml", (ROOT / "params.yaml").read_text())
    _write(
        tmp_path,
        "mid.yaml",
        "extends: base.yaml\ndeploy:\n  tasks: [goal]\n  goal: [1.0, 2.0]\n"
        "  planner: {horizon: 4, stop_cost: 0.5}\ntrain: {z_dim: 8}\n",
    )
    top = _write(
        tmp_path,
        "top.yaml",
        "extends: mid.yaml\ndeploy:\n  planner: {stop_cost: null}\ntrain: {hidden: 64}\n",
    )
    p = load_params(top)
    assert p.deploy.tasks == ["goal"] and p.deploy.goal == [1.0, 2.0]
    assert (p.deploy.planner.horizon, p.deploy.planner.stop_cost) == (4, None)
    assert p.deploy.planner.candidates == 100  # the base's, beside the overlays' keys
    assert (p.train.z_dim, p.train.hidden, p.train.lr_e) == (8, 64, 2.5e-4)
    raw, chain = read_params_file(top)
    assert EXTENDS not in raw and chain == [top, tmp_path / "mid.yaml", tmp_path / "base.yaml"]
    assert params_files(top) == chain


def test_overrides_apply_on_top_of_an_overlay():
    p = load_params(ROOT / "params-ogbench-pointmaze-large.yaml", ["deploy.planner.horizon=3"])
    assert p.deploy.planner.horizon == 3 and p.segment.window == 26  # from its base's base
    assert p.ingest.ogbench.env_id == "pointmaze-large-v0"


def test_extends_errors_are_one_line_and_name_the_file(tmp_path):
    bad_type = _write(tmp_path, "type.yaml", "extends: [params.yaml]\n")
    message = one_line_error(lambda: load_params(bad_type))
    assert str(bad_type) in message and "'extends' must name" in message
    empty = _write(tmp_path, "empty.yaml", "extends: ''\n")
    assert "'extends' must name" in one_line_error(lambda: load_params(empty))
    missing = _write(tmp_path, "missing.yaml", "extends: nope.yaml\ntrain: {z_dim: 8}\n")
    message = one_line_error(lambda: load_params(missing))
    assert str(missing) in message and str(tmp_path / "nope.yaml") in message
    assert "not found" in message
    itself = _write(tmp_path, "self.yaml", "extends: self.yaml\n")
    assert "cycle" in one_line_error(lambda: load_params(itself))
    _write(tmp_path, "a.yaml", "extends: b.yaml\n")
    _write(tmp_path, "b.yaml", "extends: ./a.yaml\n")
    message = one_line_error(lambda: load_params(tmp_path / "a.yaml"))
    assert "makes a cycle" in message and "a.yaml -> " in message and "b.yaml" in message


def test_an_overlays_bad_key_or_value_names_the_key_and_the_chain(tmp_path):
    _write(tmp_path, "params.yaml", "train: {z_dim: 8}\n")
    typo = _write(tmp_path, "typo.yaml", "extends: params.yaml\ntrain: {zdim: 3}\n")
    message = one_line_error(lambda: load_params(typo))
    assert "unknown key 'train.zdim'" in message and "(extends " in message
    assert "z_dim" in message  # the valid keys
    broken = _write(tmp_path, "broken.yaml", "extends: params.yaml\ntrain: [\n")
    assert "not valid YAML" in one_line_error(lambda: load_params(broken))
    bad = _write(tmp_path, "bad.yaml", "extends: params.yaml\n")
    message = one_line_error(lambda: load_params(bad, ["train.z_dim=many"]))
    assert "bad value for 'train.z_dim'" in message


def test_expert_params_load_through_the_same_overlay_loader(tmp_path):
    _write(tmp_path, "params.yaml", (ROOT / "experts/ant/params.yaml").read_text())
    overlay = _write(
        tmp_path,
        "params-short.yaml",
        "extends: params.yaml\nsac: {total_steps: 20000, hidden: [64]}\ncheck: {seed: 3}\n",
    )
    p = load_expert_params(overlay)
    assert (p.sac.total_steps, p.sac.hidden, p.check.seed) == (20000, [64], 3)
    assert p.sac.batch_size == AntExpertParams().sac.batch_size  # the base's
    assert load_expert_params(overlay, ["sac.batch_size=8"]).sac.batch_size == 8
    typo = _write(tmp_path, "typo.yaml", "extends: params.yaml\nsac: {lr: 1}\n")
    assert "unknown key 'sac.lr'" in one_line_error(lambda: load_expert_params(typo))
    loop = _write(tmp_path, "loop.yaml", "extends: loop.yaml\n")
    assert "cycle" in one_line_error(lambda: load_expert_params(loop))
    message = one_line_error(lambda: load_expert_params(tmp_path / "nope.yaml"))
    assert message.startswith("expert params file") and "not found" in message


def test_cli_params_prints_an_overlays_resolved_values():
    from typer.testing import CliRunner

    from cli import app

    result = CliRunner().invoke(app, ["params", "-p", str(ROOT / "params-paper.yaml")])
    assert result.exit_code == 0, result.output
    dump = yaml.safe_load(result.output)
    assert dump == load_params(ROOT / "params-paper.yaml").model_dump(mode="json")
    assert EXTENDS not in dump and dump["train"]["z_dim"] == 256


def test_an_adhoc_runs_folder_follows_the_base_file_too(tmp_path, monkeypatch):
    """`-p variant` writes under data/runs/adhoc-<key>/: the key hashes the whole chain, so a run
    after the base changed does not resume another params' run."""
    from cli import _paths

    monkeypatch.delenv("DVC_STAGE", raising=False)
    base = _write(tmp_path, "base.yaml", "train: {z_dim: 8}\n")
    variant = _write(tmp_path, "variant.yaml", "extends: base.yaml\ntrain: {hidden: 16}\n")
    before = _paths(variant, [], None, None).root
    base.write_text("train: {z_dim: 4}\n")
    after = _paths(variant, [], None, None).root
    assert before != after and before.parent == after.parent == Path("data/runs")
    assert after.name.startswith("adhoc-")
    assert _paths(base, [], None, None).root != after  # a plain file: its own bytes, as before
