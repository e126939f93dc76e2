"""The README cannot drift from the code: every command it shows runs (or at least parses), every
param, command, repository path, Python name and output path it names exists.

Commands are the `uv run ...` lines of its fenced code blocks and `uv run ...` code spans (an
`oposm <command>` span only has to name a real command). The fast tests parse each command with
the real CLI (running no stage) and validate its `-S` overrides, every `-S` anywhere and every
`section.key` span against the params schema. The slow test runs the commands for real in a
temporary folder on tiny params, in pipeline order, after the pipeline's own ingest, segment,
train and deploy (what `dvc repro` leaves in `data/`), then checks that the `data/...` paths the
README names were written. Parse-only: benchmarks, another params file (`-p params-paper.yaml`,
the paper's model sizes) and imports of data we cannot make here (LeRobot, Minari).
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
SECTIONS = ("ingest", "segment", "train", "dynamics", "validate", "deploy")
runner = CliRunner()

# --- what the README says -------------------------------------------------------------------

_FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.S | re.M)
_SPAN = re.compile(r"(?<!`)`([^`]+)`(?!`)")


def _fenced_lines() -> list[str]:
    """Lines of the fenced code blocks, `\\`-continued lines joined."""
    return [
        line for block in _FENCE.findall(README) for line in block.replace("\\\n", " ").split("\n")
    ]


def _spans() -> list[str]:
    """Code spans of the text outside fenced blocks, whitespace (line breaks) collapsed."""
    return [" ".join(s.split()) for s in _SPAN.findall(_FENCE.sub("", README)) if s.strip()]


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


def readme_commands() -> list[list[str]]:
    """Every oposm command line the README shows (`uv run ...` in code blocks and spans), in
    order, without repeats."""
    found: list[list[str]] = []
    lines = [line for line in _fenced_lines() if re.match(r"\s*(python3 -m )?uv run ", line)]
    spans = [s for s in _spans() if s.startswith("uv run ")]
    for text in [*lines, *spans]:
        if "<" in text:  # a placeholder, e.g. `oposm <stage>`
            continue
        for command in _shell_commands(text):
            args = _oposm_args(command)
            if args is not None and args not in found:
                found.append(args)
    return found


def readme_command_mentions() -> list[list[str]]:
    """Commands the text names as `oposm <command> ...` (e.g. `oposm export lerobot`)."""
    return [shlex.split(s)[1:] for s in _spans() if s.startswith("oposm ") and "<" not in s]


def _code_texts() -> list[str]:
    return [*_fenced_lines(), *_spans()]


def readme_overrides() -> list[str]:
    """Every `-S` / `--set` override anywhere in the README's code, as `key=value`."""
    found = []
    for text in _code_texts():
        try:
            tokens = shlex.split(text)
        except ValueError:
            continue
        found += [b for a, b in zip(tokens, tokens[1:], strict=False) if a in ("-S", "--set")]
    return found


def readme_param_mentions() -> list[str]:
    """Every `section.key` (maybe with `: value` or `=value`) code span, as the key."""
    keys = []
    pattern = re.compile(rf"((?:{'|'.join(SECTIONS)})\.[A-Za-z_][\w.]*)\s*(?:[:=].*)?")
    for span in _spans():
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
    if "set_" in options:
        params = options.get("params") or Path("params.yaml")
        load_params(ROOT / params, options["set_"] or [])


def test_every_command_the_readme_names_exists():
    mentions = readme_command_mentions()
    assert ["export", "lerobot"] in mentions, mentions
    for words in mentions:
        command = typer.main.get_command(app)
        for word in words:
            if not _group(command):
                break
            command = command.get_command(command.context_class(command), word)
            assert command is not None, f"README: `oposm {shlex.join(words)}`: no {word!r}"
        assert not _group(command), f"README: `oposm {shlex.join(words)}` names only a group"


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


def _repo_paths() -> list[str]:
    """Words of the README's code naming a file or folder of the repository: under one of its
    top-level entries (outputs in data/ excluded), or a top-level file by its suffix or dot."""
    tops = {p.name for p in ROOT.iterdir()} - {"data", ".venv", ".git"}
    paths = []
    for text in _code_texts():
        for token in text.split():
            token = token.strip("`'\"(),;:")
            if not re.fullmatch(r"\.?[\w-]+(\.[\w-]+)*(/[\w.-]+)*/?", token):
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


def test_every_python_name_the_readme_mentions_exists():
    names = [s for s in _spans() if re.fullmatch(r"(pipeline|stages|bench)(\.\w+)+", s)]
    for name in names:
        parts = name.split(".")
        for i in range(len(parts), 0, -1):
            try:
                obj = importlib.import_module(".".join(parts[:i]))
            except ModuleNotFoundError:
                continue
            for attr in parts[i:]:
                assert hasattr(obj, attr), f"README: {name}: no {attr} in {obj!r}"
                obj = getattr(obj, attr)
            break
        else:
            pytest.fail(f"README: {name} is not importable")


def test_readme_ingest_examples_of_other_data_name_their_dataset():
    """Another maze or source under the default name would pass for the pipeline's data."""
    for args in readme_commands():
        sets = [a.split("=", 1)[0] for a in args if "=" in a]
        if args[:1] == ["ingest"] and {"ingest.env_id", "ingest.source"} & set(sets):
            assert "ingest.name" in sets, f"README: oposm {shlex.join(args)} keeps the default name"


def test_the_goal_in_a_wall_example_is_a_wall_of_the_default_maze():
    from pipeline.envs.maze import layout_cell
    from pipeline.envs.spec import make_env_spec

    goals = [o.split("=", 1)[1] for o in readme_overrides() if o.startswith("deploy.goal=")]
    assert goals, "the README shows no deploy.goal example"
    layout = make_env_spec(_defaults()["ingest"]["env_id"]).layout
    for goal in goals:
        row, col = layout_cell(layout, *yaml.safe_load(goal))
        assert layout["maze_map"][row][col] == 1, f"deploy.goal={goal} is free cell {row, col}"


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


def _runs_here(args: list[str]) -> bool:
    """Whether the slow test runs a README command for real (else it is parse-only)."""
    if not args or args[0] not in ORDER or "-p" in args or "--params" in args:
        return False
    sources = [a.split("=", 1)[1] for a in args if a.startswith("ingest.source=")]
    return all(s in ("maze", "d4rl") for s in sources)


def _write_d4rl_file(args: list[str]) -> None:
    """The hdf5 file a README D4RL import names, made from a tiny generated dataset of its maze."""
    from pipeline.envs.expert import ExpertConfig
    from pipeline.envs.generate import dataset_info, generate_episodes
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
