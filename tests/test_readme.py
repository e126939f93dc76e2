"""The README and docs/*.md cannot drift from the code: every command they show runs (or at least
parses), every param, command, repository path, Python name and output path they name exists,
every relative link resolves, and every default they state is the code's.

Commands are the `uv run ...` lines of its fenced code blocks and `uv run ...` code spans (an
`oposm <command>` span only has to name a real command). The fast tests parse each command with
the real CLI (running no stage) and validate its `-S` overrides, every `-S` anywhere and every
`section.key` span against the params schema. The slow test runs the commands for real in a
temporary folder on tiny params, in pipeline order, after the pipeline's own ingest, segment,
train and deploy (what `dvc repro` leaves in `data/`), then checks that the `data/...` paths the
README names were written. Parse-only: benchmarks, another params file (`-p params-paper.yaml`,
the paper's model sizes), imports of data we cannot make here (LeRobot, Minari) and the stages
that read such an import (the same `ingest.name`). The docs' commands are parse-only.

A default is stated one way, `` `section.key` (default `value`) ``, so that it can be checked
against the pydantic default in pipeline/config.py.
"""

from __future__ import annotations

import importlib
import re
import shlex
from pathlib import Path

import pytest
import typer.core
import typer.main
import yaml
from typer.testing import CliRunner

from cli import app
from pipeline.config import load_params

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
DOCS = sorted((ROOT / "docs").glob("*.md"))
# Every page the checks read: the README and the docs, by path relative to the repository.
PAGES = {"README.md": README} | {str(p.relative_to(ROOT)): p.read_text() for p in DOCS}
SECTIONS = ("ingest", "segment", "train", "dynamics", "bc", "gcbc", "validate", "deploy")
runner = CliRunner()

# --- what the README says -------------------------------------------------------------------

_FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.S | re.M)
_SPAN = re.compile(r"(?<!`)`([^`]+)`(?!`)")


def _fenced_lines(text: str = README) -> list[str]:
    """Lines of the fenced code blocks, `\\`-continued lines joined."""
    return [
        line for block in _FENCE.findall(text) for line in block.replace("\\\n", " ").split("\n")
    ]


def _spans(text: str = README) -> list[str]:
    """Code spans of the text outside fenced blocks, whitespace (line breaks) collapsed."""
    return [" ".join(s.split()) for s in _SPAN.findall(_FENCE.sub("", text)) if s.strip()]


def _shell_commands(line: str) -> list[list[str]]:
    """The simple commands of a shell line (split at &&, ;, |), comments dropped."""
    try:
        tokens = shlex.split(line, comments=True)
    except ValueError:
        return []
    commands, current = [], []
    for token in tokens:
        if token in ("&&", "||", ";", "|"):
            commands.append(current)
            current = []
        else:
            current.append(token)
    return [c for c in [*commands, current] if c]


def _oposm_args(command: list[str]) -> list[str] | None:
    """The arguments of an `oposm` command (`uv run oposm ...`, `accelerate launch ... cli.py
    ...`), else None."""
    for i, token in enumerate(command):
        if token in ("oposm", "cli.py"):
            return command[i + 1 :]
    return None


def readme_commands(text: str = README) -> list[list[str]]:
    """Every oposm command line a page shows (`uv run ...` in code blocks and spans), in
    order, without repeats."""
    found: list[list[str]] = []
    lines = [line for line in _fenced_lines(text) if re.match(r"\s*(python3 -m )?uv run ", line)]
    spans = [s for s in _spans(text) if s.startswith("uv run ")]
    for line in [*lines, *spans]:
        if "<" in line or "..." in line:  # a placeholder, e.g. `oposm <stage>`, `oposm bench ...`
            continue
        for command in _shell_commands(line):
            args = _oposm_args(command)
            if args is not None and args not in found:
                found.append(args)
    return found


def readme_command_mentions(text: str = README) -> list[list[str]]:
    """Commands the text names as `oposm <command> ...` (e.g. `oposm export lerobot`)."""
    return [
        shlex.split(s)[1:]
        for s in _spans(text)
        if s.startswith("oposm ") and "<" not in s and "..." not in s
    ]


def _code_texts(text: str = README) -> list[str]:
    return [*_fenced_lines(text), *_spans(text)]


# The generic form of an override, as the text explains it: not a real key.
_PLACEHOLDERS = {"section.key=value"}


def readme_overrides(page: str = README) -> list[str]:
    """Every `-S` / `--set` override anywhere in a page's code, as `key=value`."""
    found = []
    for text in _code_texts(page):
        if re.search(r"\b(oposm|cli\.py) expert\b", text):  # the expert's own params
            continue
        try:
            tokens = shlex.split(text)
        except ValueError:
            continue
        found += [
            b
            for a, b in zip(tokens, tokens[1:], strict=False)
            if a in ("-S", "--set") and b not in _PLACEHOLDERS
        ]
    return found


def readme_param_mentions(text: str = README) -> list[str]:
    """Every `section.key` (maybe with `: value` or `=value`) code span, as the key."""
    keys = []
    pattern = re.compile(rf"((?:{'|'.join(SECTIONS)})\.[A-Za-z_][\w.]*)\s*(?:[:=].*)?")
    for span in _spans(text):
        match = pattern.fullmatch(span)
        if match and not re.search(r"\.(json|rrd|csv|py|yaml|mcap)$", match.group(1)):
            keys.append(match.group(1))
    return keys


# --- the CLI and the params ---------------------------------------------------------------------


def _group(command) -> bool:
    return isinstance(command, typer.core.TyperGroup)


def parse(args: list[str]):
    """Resolve `oposm ARGS` to its command and parsed options, running nothing.

    Raises:
        AssertionError: an unknown command.
        click's UsageError (typer's copy): an unknown or missing option or argument, a bad value.
    """
    command = typer.main.get_command(app)
    ctx = command.context_class(command, info_name="oposm")
    rest = list(args)
    while _group(command):
        assert rest, f"oposm {shlex.join(args)}: a command group needs a command"
        name, *rest = rest
        sub = command.get_command(ctx, name)
        assert sub is not None, f"oposm {shlex.join(args)}: no command {name!r}"
        parent, command = ctx, sub
        ctx = command.context_class(command, info_name=name, parent=parent)
    return command, command.make_context(ctx.info_name, rest, parent=ctx.parent).params


def _defaults() -> dict:
    return load_params(ROOT / "params.yaml").model_dump()


def is_param(key: str, defaults: dict) -> bool:
    node = defaults
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return True


# --- fast: everything parses and every name exists ----------------------------------------------


def test_the_readme_shows_commands():
    names = {args[0] for args in readme_commands() if args}
    assert {"ingest", "deploy", "inspect", "params"} <= names, names


@pytest.mark.parametrize("args", readme_commands(), ids=" ".join)
def test_every_readme_command_parses_and_its_params_validate(args, monkeypatch):
    monkeypatch.chdir(ROOT)
    if "--help" in args:
        result = runner.invoke(app, args)
        assert result.exit_code == 0 and "Usage" in result.output, result.output
        return
    _, options = parse(args)
    if "set_" in options and args[0] == "expert":  # its own params file
        from pipeline.ant_expert.config import default_params_path, load_expert_params

        params = options.get("params") or default_params_path(options["robot"])
        load_expert_params(ROOT / params, options["set_"] or [])
    elif "set_" in options:
        params = options.get("params") or Path("params.yaml")
        load_params(ROOT / params, options["set_"] or [])


def _assert_commands_exist(mentions: list[list[str]], where: str) -> None:
    """Each `oposm <words>` that `where` names is a command of the CLI (not only a group)."""
    for words in mentions:
        command = typer.main.get_command(app)
        for word in words:
            if not _group(command):
                break
            command = command.get_command(command.context_class(command), word)
            assert command is not None, f"{where}: `oposm {shlex.join(words)}`: no {word!r}"
        assert not _group(command), f"{where}: `oposm {shlex.join(words)}` names only a group"


def test_every_command_the_readme_names_exists():
    mentions = readme_command_mentions()
    assert ["export", "lerobot"] in mentions, mentions
    _assert_commands_exist(mentions, "README")


def test_every_override_in_the_readme_is_a_param_with_a_valid_value():
    defaults = _defaults()
    overrides = readme_overrides()
    assert len(overrides) > 5, overrides
    for override in overrides:
        key = override.split("=", 1)[0]
        assert is_param(key, defaults), f"README: -S {override}: {key} is not a param"
        load_params(ROOT / "params.yaml", [override])  # the value too (UserError if not)


def test_every_section_key_the_readme_mentions_is_a_param():
    defaults = _defaults()
    mentions = readme_param_mentions()
    assert mentions, "no section.key mentions found: the extraction is broken"
    missing = [key for key in mentions if not is_param(key, defaults)]
    assert not missing, f"README names params that do not exist: {missing}"


# Files that exist only after a run, not in a checkout.
_GENERATED = {"dvc.lock"}
_REPO_SUFFIXES = (".py", ".yaml", ".yml", ".toml", ".lock", ".md", ".proto", ".cfg")


def _repo_paths(page: str = README) -> list[str]:
    """Words of a page's code naming a file or folder of the repository: under one of its
    top-level entries (outputs in data/ excluded), or a top-level file by its suffix or dot."""
    tops = {p.name for p in ROOT.iterdir()} - {"data", ".venv", ".git"}
    paths = []
    for text in _code_texts(page):
        for token in text.split():
            token = token.strip("`'\"(),;:")
            if not re.fullmatch(r"\.?[\w-]+(\.[\w-]+)*(/[\w.-]+)*/?", token):
                continue
            if re.fullmatch(r"\.[A-Za-z0-9]+", token):  # a file type (`.npz`), not a file
                continue
            if "/" in token:
                if token.split("/")[0] in tops:
                    paths.append(token)
            elif token.endswith(_REPO_SUFFIXES) or token.startswith("."):
                paths.append(token)
    return sorted(set(paths) - _GENERATED)


def test_every_repository_path_the_readme_names_exists():
    paths = _repo_paths()
    assert {"params.yaml", "pipeline/recording/step.proto"} <= set(paths), paths
    missing = [p for p in paths if not (ROOT / p).exists()]
    assert not missing, f"README names files that are not in the repository: {missing}"


def _python_names(page: str) -> list[str]:
    """The dotted names of the project's Python objects a page shows in code spans."""
    return [s for s in _spans(page) if re.fullmatch(r"(pipeline|stages|bench)(\.\w+)+", s)]


def _check_python_names(page: str, where: str) -> None:
    for name in _python_names(page):
        parts = name.split(".")
        for i in range(len(parts), 0, -1):
            try:
                obj = importlib.import_module(".".join(parts[:i]))
            except ModuleNotFoundError:
                continue
            for attr in parts[i:]:
                assert hasattr(obj, attr), f"{where}: {name}: no {attr} in {obj!r}"
                obj = getattr(obj, attr)
            break
        else:
            pytest.fail(f"{where}: {name} is not importable")


def test_readme_ingest_examples_of_other_data_name_their_dataset():
    """Another maze or source under the default name would pass for the pipeline's data."""
    for args in readme_commands():
        sets = [a.split("=", 1)[0] for a in args if "=" in a]
        if args[:1] == ["ingest"] and {"ingest.env_id", "ingest.source"} & set(sets):
            assert "ingest.name" in sets, f"README: oposm {shlex.join(args)} keeps the default name"


def test_the_goal_in_a_wall_example_is_a_wall_of_the_default_maze():
    from pipeline.envs.maze.env import layout_cell
    from pipeline.envs.spec import make_env_spec

    goals = [o.split("=", 1)[1] for o in readme_overrides() if o.startswith("deploy.goal=")]
    assert goals, "the README shows no deploy.goal example"
    layout = make_env_spec(_defaults()["ingest"]["env_id"]).layout
    for goal in goals:
        row, col = layout_cell(layout, *yaml.safe_load(goal))
        assert layout["maze_map"][row][col] == 1, f"deploy.goal={goal} is free cell {row, col}"


# --- docs/*.md: the same checks, parse-only -------------------------------------------------


def test_the_docs_exist():
    names = {p.name for p in DOCS}
    expected = {"pipeline.md", "configuration.md", "data.md", "rerun.md", "experiments.md",
                "reproducing.md", "performance.md", "ant-expert.md", "development.md",
                "references.md"}  # fmt: skip
    assert expected <= names, f"docs/ lacks {sorted(expected - names)}"


def _doc_commands() -> list[tuple[str, list[str]]]:
    return [
        (page, args)
        for page in PAGES
        if page != "README.md"
        for args in readme_commands(PAGES[page])
    ]


@pytest.mark.parametrize(
    ("page", "args"), _doc_commands(), ids=[f"{p}: {' '.join(a)}" for p, a in _doc_commands()]
)
def test_every_docs_command_parses_and_its_params_validate(page, args, monkeypatch):
    test_every_readme_command_parses_and_its_params_validate(args, monkeypatch)


@pytest.mark.parametrize("page", list(PAGES))
def test_every_command_a_page_names_exists(page):
    _assert_commands_exist(readme_command_mentions(PAGES[page]), page)


@pytest.mark.parametrize("page", list(PAGES))
def test_every_override_on_a_page_is_a_param_with_a_valid_value(page):
    defaults = _defaults()
    for override in readme_overrides(PAGES[page]):
        key = override.split("=", 1)[0]
        assert is_param(key, defaults), f"{page}: -S {override}: {key} is not a param"
        load_params(ROOT / "params.yaml", [override])


@pytest.mark.parametrize("page", list(PAGES))
def test_every_section_key_a_page_mentions_is_a_param(page):
    defaults = _defaults()
    missing = [k for k in readme_param_mentions(PAGES[page]) if not is_param(k, defaults)]
    assert not missing, f"{page} names params that do not exist: {missing}"


@pytest.mark.parametrize("page", list(PAGES))
def test_every_repository_path_a_page_names_exists(page):
    missing = [p for p in _repo_paths(PAGES[page]) if not (ROOT / p).exists()]
    assert not missing, f"{page} names files that are not in the repository: {missing}"


def test_the_python_name_check_sees_names_and_refuses_wrong_ones():
    assert "pipeline.errors.UserError" in _python_names(PAGES["docs/development.md"])
    _check_python_names("`pipeline.errors.UserError` and `pipeline.io`", "page")
    with pytest.raises(AssertionError, match="no NoSuchError"):
        _check_python_names("`pipeline.errors.NoSuchError`", "page")
    with pytest.raises(AssertionError, match="no no_such_stage"):
        _check_python_names("`stages.no_such_stage`", "page")


# Only the pages that name Python objects: a page naming none would check nothing.
@pytest.mark.parametrize("page", [p for p in PAGES if _python_names(PAGES[p])])
def test_every_python_name_a_page_mentions_exists(page):
    _check_python_names(PAGES[page], page)


# --- links ----------------------------------------------------------------------------------

_LINK = re.compile(r"(?<!!)\[(?:[^\]\n]|\n(?!\n))*?\]\(([^)\s]+)\)")


def slug(heading: str) -> str:
    """A heading's anchor as a code host (GitHub) makes it (scripts/params_doc.py does the same)."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(text: str) -> set[str]:
    """The anchors of a page's headings (outside code blocks); repeats get -1, -2, ..."""
    seen: dict[str, int] = {}
    out = set()
    for heading in re.findall(r"^#{1,6} +(.+?) *#*$", _FENCE.sub("", text), re.M):
        base = slug(heading)
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def links(text: str) -> list[str]:
    """Link targets of a page's text (outside code blocks and spans)."""
    prose = _SPAN.sub("", _FENCE.sub("", text))
    return _LINK.findall(prose)


def test_the_link_extraction_sees_links():
    text = "See [the docs](docs/a.md#b), `[not](this.md)`, ![img](x.png) and\n[two\nlines](c.md)."
    assert links(text) == ["docs/a.md#b", "c.md"]
    assert anchors("# A `b.c` title\n## A `b.c` title\n```\n# not\n```\n") == {
        "a-bc-title", "a-bc-title-1"}  # fmt: skip


def _resolves(page: str, target: str) -> bool:
    """Whether a relative link of `page` names a file or folder inside the repository, and, for a
    Markdown page, one of its headings' anchors."""
    path, _, anchor = target.partition("#")
    file = ((ROOT / page).parent / path).resolve() if path else (ROOT / page).resolve()
    if not file.is_relative_to(ROOT) or not file.exists():
        return False
    return not anchor or file.suffix != ".md" or anchor in anchors(file.read_text())


@pytest.mark.parametrize("page", list(PAGES))
def test_every_relative_link_resolves(page):
    targets = [t for t in links(PAGES[page]) if not re.match(r"[a-z]+:", t)]  # not https:
    broken = [t for t in targets if not _resolves(page, t)]
    assert not broken, f"{page}: links that do not resolve: {broken}"


def test_the_readme_links_into_docs_and_results():
    targets = links(README)
    assert {f"docs/{p.name}" for p in DOCS} <= set(targets), "the README must list every page"
    assert any(t.startswith("results/") for t in targets), targets


def test_nothing_refers_to_a_file_outside_the_repository():
    """No tracked text names a design note, a reference list or a sibling folder that the
    repository does not hold."""
    import subprocess

    names = ["DESIGN" + ".md", "REFERENCES" + ".md", "shared" + "/"]
    try:
        files = subprocess.run(
            ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout.split()
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    found = []
    for name in files:
        path = ROOT / name
        if name.startswith("data/") or not path.is_file() or path.stat().st_size > 5_000_000:
            continue
        try:
            text = path.read_text()
        except UnicodeDecodeError:
            continue
        found += [f"{name}: {n}" for n in names if n in text]
    assert not found, found


# --- the README's size and the defaults the pages state -------------------------------------


def test_the_readme_is_a_front_door():
    lines = README.count("\n")
    assert lines <= 200, f"README.md has {lines} lines: move detail into docs/ (at most 200)"


# `train.select` (default `st_nll_prior`): the one way a page states a default.
_DEFAULT = re.compile(r"`((?:" + "|".join(SECTIONS) + r")\.[\w.]+)`\s+\(default\s+`([^`]+)`")
# A default stated another way: `key: value` or `key=value`, then "default" close behind.
_OTHER_DEFAULT = re.compile(
    r"`((?:" + "|".join(SECTIONS) + r")\.[\w.]+)\s*[:=][^`]*`[^`\n]{0,12}\bdefault\b"
)


def stated_defaults(text: str) -> list[tuple[str, str]]:
    """(key, value) of every `` `key` (default `value`) `` on a page."""
    return _DEFAULT.findall(_FENCE.sub("", text))


def _code_default(key: str):
    from pipeline.config import Params

    node = Params().model_dump(by_alias=True)
    for part in key.split("."):
        node = node[part]
    return node


def test_stated_defaults_are_found():
    statements = [s for text in PAGES.values() for s in stated_defaults(text)]
    assert len(statements) >= 5, statements
    assert stated_defaults("`train.select` (default\n`st_nll_prior`, the prior's)") == [
        ("train.select", "st_nll_prior")
    ]


@pytest.mark.parametrize("page", list(PAGES))
def test_every_default_a_page_states_is_the_codes(page):
    defaults = _defaults()
    wrong = []
    for key, value in stated_defaults(PAGES[page]):
        assert is_param(key, defaults), f"{page}: `{key}` (default ...): no such param"
        if yaml.safe_load(value) != _code_default(key):
            wrong.append(f"`{key}` (default `{value}`): the code's is {_code_default(key)!r}")
    assert not wrong, f"{page}: {wrong}"


@pytest.mark.parametrize("page", list(PAGES))
def test_defaults_are_stated_the_checked_way(page):
    """`train.e_prior: ema` (the default) cannot be checked; `train.e_prior` (default `ema`) is."""
    others = _OTHER_DEFAULT.findall(_FENCE.sub("", PAGES[page]))
    assert not others, f"{page}: state these as `key` (default `value`): {others}"


# --- slow: the commands run -----------------------------------------------------------------

TINY = {
    "ingest": {"episodes": 6, "episode_steps": 150},
    "segment": {"window": 20},
    "train": {"z_dim": 4, "hidden": 16, "max_steps": 20, "eval_every": 10, "val_windows": 50},
    "dynamics": {"hidden": 16, "max_steps": 50, "eval_every": 25, "val_transitions": 200},
    "validate": {"starts": 5, "skills": 2, "repeats": 2, "particles": 8, "record_starts": 1},
    "deploy": {
        "episodes": 2,
        "num_envs": 2,
        "max_steps": 40,
        "record_episodes": 1,
        "planner": {"horizon": 2, "candidates": 8, "elites": 2, "iterations": 2},
    },
}
# Pipeline order: a command runs after those that make its inputs.
ORDER = [
    "--help", "params", "causal-example", "ingest", "inspect", "segment", "train", "dynamics",
    "validate", "deploy", "view", "export",
]  # fmt: skip
# Appended to a README command that already runs ad hoc, to keep it small.
TINY_EXTRA = {"deploy": ["-S", "deploy.episodes=2"], "view": ["--dry-run"]}
# The data the pipeline's own commands leave, which the README's examples read.
SETUP = [["ingest"], ["segment"], ["train"], ["deploy"]]


def _sets(args: list[str], key: str) -> list[str]:
    """The values a command's `-S key=value` overrides give `key`."""
    return [a.split("=", 1)[1] for a in args if a.startswith(f"{key}=")]


def _imports_we_cannot_make() -> set[str]:
    """The `ingest.name` of each README import whose data cannot be made here (LeRobot, Minari):
    the stages that read that dataset are parse-only too."""
    return {
        name
        for args in readme_commands()
        if args[:1] == ["ingest"]
        and not all(s in ("maze", "d4rl") for s in _sets(args, "ingest.source"))
        for name in _sets(args, "ingest.name")
    }


def _runs_here(args: list[str]) -> bool:
    """Whether the slow test runs a README command for real (else it is parse-only)."""
    if not args or args[0] not in ORDER or "-p" in args or "--params" in args:
        return False
    if set(_sets(args, "ingest.name")) & _imports_we_cannot_make():
        return False
    return all(s in ("maze", "d4rl") for s in _sets(args, "ingest.source"))


def _write_d4rl_file(args: list[str]) -> None:
    """The hdf5 file a README D4RL import names, made from a tiny generated dataset of its maze."""
    from pipeline.envs.maze.expert import ExpertConfig
    from pipeline.envs.maze.generate import dataset_info, generate_episodes
    from pipeline.sources import write_d4rl

    sets = dict(a.split("=", 1) for a in args if "=" in a)
    env_id, path = sets["ingest.d4rl.env_id"], sets["ingest.d4rl.path"]
    info = dataset_info(env_id, "d4rl", 0, ExpertConfig(), 4, 150)
    write_d4rl(path, generate_episodes(env_id, 4, 150, 0, ExpertConfig()), info)


def _goal_in_a_wall() -> list[str]:
    spans = [s for s in _spans() if "deploy.goal=" in s and not s.startswith(("oposm", "uv"))]
    assert spans, "the README's goal-in-a-wall example is gone"
    return ["deploy", *shlex.split(spans[0])]


def _data_paths() -> list[str]:
    """`data/...` paths the README names, as glob patterns (placeholders -> *)."""
    found = set()
    for text in _code_texts():
        for token in text.split():
            token = token.strip("`'\"(),;:")
            if token.startswith("data/"):
                pattern = token.replace("<name>", "pointmaze-medium")
                found.add(re.sub(r"<[^>]+>", "*", pattern).rstrip("/"))
    return sorted(found)


@pytest.mark.slow
def test_every_readme_command_runs(tmp_path, monkeypatch):
    import torch

    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    for section, values in TINY.items():
        for key, value in values.items():
            if isinstance(value, dict):
                params[section][key].update(value)
            else:
                params[section][key] = value
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("DVC_STAGE", raising=False)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # on a loaded 2-core machine two intra-op threads are 20x slower
    ran: list[list[str]] = []

    def run(args: list[str], expect: int = 0) -> str:
        result = runner.invoke(app, args)
        assert result.exit_code == expect, f"oposm {shlex.join(args)}:\n{result.output}"
        ran.append(args)
        return result.output

    try:
        for args in SETUP:
            run(args)
        commands = sorted(
            (a for a in readme_commands() if _runs_here(a) and a not in SETUP),
            key=lambda a: ORDER.index(a[0]),
        )
        for args in commands:
            if any(a.startswith("ingest.source=d4rl") for a in args):
                _write_d4rl_file(args)
            extra = TINY_EXTRA.get(args[0], []) if "-S" in args or args[0] == "view" else []
            run(args + extra)
        stderr = runner.invoke(app, _goal_in_a_wall()).stderr.strip().splitlines()
        assert len(stderr) == 1 and "inside a wall" in stderr[0], stderr
    finally:
        torch.set_num_threads(threads)

    names = {args[0] for args in ran}
    assert {"ingest", "inspect", "segment", "train", "deploy", "view"} <= names, names
    missing = [p for p in _data_paths() if not list(tmp_path.glob(p))]
    assert not missing, f"README names data the commands did not write: {missing}"
