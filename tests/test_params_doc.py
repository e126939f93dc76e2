"""docs/configuration.md is what scripts/params_doc.py writes from the pydantic models: a changed
description, default, type, constraint or variant file without a regenerated page fails here."""

import copy
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
REGENERATE = "uv run python scripts/params_doc.py"


def _module():
    spec = importlib.util.spec_from_file_location("params_doc", ROOT / "scripts/params_doc.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_configuration_page_is_the_generators_output():
    doc = _module()
    current = doc.PAGE.read_text()
    assert doc.render(current) == current, f"docs/configuration.md is out of date: {REGENERATE}"


def test_the_page_keeps_its_introduction_and_lists_every_key():
    from pipeline.config import Params, load_params

    doc = _module()
    text = doc.PAGE.read_text()
    intro = text.partition(doc.MARKER)[0]
    assert "extends: params.yaml" in intro and "-S" in intro, "the hand-written intro is gone"

    def keys(values: dict, prefix: str = "") -> list[str]:
        out = []
        for key, value in values.items():
            if isinstance(value, dict) and value:
                out += keys(value, f"{prefix}{key}.")
            else:
                out.append(f"{prefix}{key}")
        return out

    every = keys(Params().model_dump(by_alias=True))
    assert every == keys(load_params(ROOT / "params.yaml").model_dump(by_alias=True))
    missing = [k for k in every if f"| `{k}` |" not in text]
    assert not missing, f"docs/configuration.md has no row for {missing}"


def test_a_changed_description_or_default_changes_the_page(monkeypatch):
    """What the page test relies on: the generated text follows the models."""
    from pipeline.config import TrainParams

    doc = _module()
    before = doc.reference()
    field = TrainParams.model_fields["select"]
    changed = copy.copy(field)
    changed.default, changed.description = "st_nll", "Another description."
    monkeypatch.setitem(TrainParams.model_fields, "select", changed)
    after = doc.reference()
    monkeypatch.setitem(TrainParams.model_fields, "select", field)
    assert "| `train.select` |" in after and after != before
    assert "Another description." in after and "`st_nll` | Another" in after


def test_a_table_cell_escapes_pipes_and_tags_outside_code():
    doc = _module()
    assert doc._cell("a | b `x|<y>` models/<name>/") == "a \\| b `x\\|<y>` models/&lt;name>/"
    assert doc.slug("`sac.phases[]`") == "sacphases"
    assert doc.slug("What each variant changes") == "what-each-variant-changes"
