"""The code dependencies of every DVC stage, generated from the import graph, so they cannot drift.

A stage's code is the file its command runs (`oposm <stage>`: `stages/<stage>.py`; `python
<script>`: the script) and every project module that file imports, transitively (an AST scan,
imports inside functions included; `from package import name` also counts `package/name.py`).
Each stage's `deps` list those files, in place of the code entries it had; its data entries
(`data/...`, `results/...`, anything outside the code folders) are kept as they are, first.

Two kinds of module are left out, because they cannot change what a stage computes:
`PLUMBING` (paths, errors, atomic writes, the params' validation, MKL's reproducible mode: the
environment a lock is made in, rather than one stage's code) and package `__init__.py` files
that hold only a docstring. The packages in `FOLDERS` are listed as their folder: their modules
go together (the skill model, the planners, the MCAP format, the importers), and a folder entry
covers its data files too (the published numbers' TOML files beside their loader).

    uv run python scripts/dvc_deps.py            # rewrite the deps of every dvc.yaml
    uv run python scripts/dvc_deps.py --check    # exit 1, naming each stage, if any is out of date
    uv run python scripts/dvc_deps.py --record   # after a rewrite that moved no code: the locks

A rewrite that changes the entries but not the code they cover (a module moved into a listed
folder, say) leaves a lock recording the old entries. `--record` writes today's hashes for the
new entries of a stage only where every old entry covering the same files records today's
content, or where the new entry is a file moved unchanged (its content is what the lock recorded
for a file no longer listed): the code the stage ran is exactly today's. Anything else stays as
it was, so a stage whose code did change stays stale. Same as `dvc commit`, without needing the
stage's outputs.
"""

from __future__ import annotations

import argparse
import ast
import functools
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
PIPELINES = (
    "dvc.yaml",
    "experiments/dvc.yaml",
    "experiments/ogbench/dvc.yaml",
    "experiments/antmaze/dvc.yaml",
    "experiments/manipulation/dvc.yaml",
)  # the main job, the paper's experiments, OGBench's point mazes, the ant mazes, manipulation
PACKAGES = ("pipeline", "stages")  # what an import can reach in the project
CODE = ("pipeline/", "stages/", "scripts/", "bench/", "cli.py")  # what a code entry starts with
PLUMBING = frozenset({
    "pipeline/__init__.py",  # sets MKL's reproducible mode (cpu_math), like the locked versions
    "pipeline/cpu_math.py",
    "stages/__init__.py",
    "pipeline/errors.py",
    "pipeline/paths.py",
    "pipeline/io.py",
    "pipeline/devices.py",
    "pipeline/config.py",  # the params are each stage's `params:` (params.yaml = the defaults)
    "pipeline/readback.py",  # checks of files read back: a valid file's values pass unchanged
})  # fmt: skip
LOCK_KEYS = ("path", "hash", "md5", "size", "nfiles")  # a lock entry's keys, in DVC's order
# Entry points renamed without changing what they run: (old, new) command prefixes. `--record`
# writes a stage's new command into its lock where the locked one, so renamed, is exactly it.
COMMAND_MOVES = (
    ("python scripts/antmaze_report.py", "oposm report antmaze"),
    ("python scripts/manipulation_report.py", "oposm report manipulation"),
    ("python scripts/ogbench_point_report.py", "oposm report ogbench-point"),
    ("oposm results", "oposm report experiments"),
)
FOLDERS = (
    "pipeline/model",
    "pipeline/planning",
    "pipeline/recording",
    "pipeline/sources",
    "pipeline/evaluation/published",  # its loader and data files (the published numbers)
)


def _module_file(name: str) -> Path | None:
    parts = name.split(".")
    if parts[0] not in PACKAGES:
        return None
    base = ROOT.joinpath(*parts)
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.exists():
            return candidate
    return None


@functools.cache  # one parse per file and run: hundreds of stages share most of their code
def imports(path: Path) -> frozenset[Path]:
    """The project files `path` imports (each package's `__init__.py` on the way included)."""
    found: set[Path] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
        for name in names:
            parts = name.split(".")
            for i in range(1, len(parts) + 1):  # importing a.b.c runs a/__init__, a/b/__init__
                module = _module_file(".".join(parts[:i]))
                if module is not None:
                    found.add(module)
    return frozenset(found)


@functools.cache
def docstring_only(path: Path) -> bool:
    return all(isinstance(n, ast.Expr) for n in ast.parse(path.read_text()).body)


def rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def code_of(entry: Path) -> set[Path]:
    """The project files `entry` runs: itself and everything it imports, transitively, less
    `PLUMBING` and docstring-only files."""
    seen: set[Path] = set()
    todo = [entry]
    while todo:
        path = todo.pop()
        if path in seen or rel(path) in PLUMBING or docstring_only(path):
            continue
        seen.add(path)
        todo += imports(path) - seen
    return seen


def entry_point(cmd: str) -> Path:
    """The file a stage's command runs: `oposm <stage>` -> stages/<stage>.py, `oposm report
    <benchmark>` -> stages/<benchmark>_report.py, `python <script>` -> the script."""
    words = cmd.split()
    if words[:2] == ["oposm", "report"]:  # a benchmark's page: stages/<benchmark>_report.py
        return ROOT / "stages" / f"{words[2].replace('-', '_')}_report.py"
    if words[0] == "oposm":
        return ROOT / "stages" / f"{words[1]}.py"
    if words[0] == "python" and words[1].endswith(".py"):
        return ROOT / words[1]
    raise ValueError(f"unknown command (neither `oposm <stage>` nor `python <file>.py`): {cmd}")


@functools.cache
def code_deps(cmd: str) -> tuple[str, ...]:
    """The code entries of a stage running `cmd`: its entry point first, then its other files
    and `FOLDERS`, sorted."""
    entry = entry_point(cmd)
    listed = set()
    for path in code_of(entry) - {entry}:
        name = rel(path)
        listed.add(next((f for f in FOLDERS if name.startswith(f + "/")), name))
    return (rel(entry), *sorted(listed))


def is_code(entry: str) -> bool:
    return entry.startswith(CODE)


# --- the dvc.yaml files, rewritten as text (their comments and layout stay) ----------------------


@dataclass
class DepsBlock:
    """One stage's `deps:` list in a dvc.yaml: its item lines `[start, end)`, their indent."""

    stage: str
    cmd: str
    start: int
    end: int
    indent: str


def deps_blocks(text: str, stages: dict) -> list[DepsBlock]:
    """The `deps:` list of each stage in `text`, in file order. `stages`: the parsed `stages:`
    mapping (each stage's command, from its `do:` body where it loops)."""
    lines = text.splitlines()
    blocks, stage = [], None
    for i, line in enumerate(lines):
        top = re.fullmatch(r"  ([A-Za-z0-9_-]+):\s*(#.*)?", line)
        if top:
            stage = top[1]
            continue
        key = re.fullmatch(r"( *)deps:\s*", line)
        if not key or stage is None:
            continue
        item = re.compile(rf"({key[1]}|{key[1]}  )- ")
        comment = re.compile(rf"({key[1]}|{key[1]}  )#")  # a comment inside the list
        end = i + 1
        while end < len(lines) and (item.match(lines[end]) or comment.match(lines[end])):
            end += 1
        first = next((line for line in lines[i + 1 : end] if item.match(line)), None)
        indent = item.match(first)[1] if first else key[1]
        spec = stages[stage].get("do", stages[stage])
        blocks.append(DepsBlock(stage, spec["cmd"], i + 1, end, indent))
    return blocks


def _entry(line: str) -> str:
    """A deps line's path ("" for a comment line)."""
    if line.lstrip().startswith("#"):
        return ""
    return line.split("- ", 1)[1].split(" #")[0].strip()


def rewritten(text: str) -> tuple[str, list[str]]:
    """`text` (a dvc.yaml) with each stage's code entries generated; the stages that changed."""
    stages = yaml.safe_load(text)["stages"]
    lines = text.splitlines()
    changed = []
    for block in reversed(deps_blocks(text, stages)):
        old = lines[block.start : block.end]
        data = [line for line in old if not is_code(_entry(line))]
        new = data + [f"{block.indent}- {path}" for path in code_deps(block.cmd)]
        if new != old:
            changed.append(block.stage)
            lines[block.start : block.end] = new
    return "\n".join(lines) + "\n", sorted(changed)


# --- the locks: new entries that cover unchanged code ---------------------------------------------


def _overlap(a: str, b: str) -> bool:
    """Whether entries `a` and `b` cover some file in common (one is, or holds, the other)."""
    return a == b or a.startswith(b.rstrip("/") + "/") or b.startswith(a.rstrip("/") + "/")


def _same_file(locked: dict, today: str | None) -> bool:
    """Whether a lock entry records a file (not a folder) whose content is `today`'s hash."""
    md5 = locked.get("md5")
    return today is not None and md5 == today and not md5.endswith(".dir")


def moved_command(cmd: str) -> str:
    """`cmd` with its entry point renamed by `COMMAND_MOVES` (the same arguments after it)."""
    for old, new in COMMAND_MOVES:
        if cmd == old or cmd.startswith(old + " "):
            return new + cmd[len(old) :]
    return cmd


def record(pipeline: str, root: Path = ROOT) -> list[str]:
    """Write into `pipeline`'s lock a stage's command where only its entry point was renamed
    (`COMMAND_MOVES`), and today's hash of each code entry its lock lacks, where every
    old entry it replaces (covering some of the same files, and no longer listed) records
    today's content, or where it is a file that moved unchanged (a listed file whose content is
    that of an entry no longer listed); drop the old code entries no longer listed. One line
    per entry written, left, or dropped."""
    from dvc.dependency import Dependency
    from dvc.repo import Repo
    from dvc.utils.serialize import dump_yaml, load_yaml

    lock_path = (root / pipeline).with_suffix(".lock")
    lock = load_yaml(lock_path)  # DVC's own reader and writer: the lock's layout stays
    done = []
    with Repo(str(root)) as repo:
        stages = {s.name: s for s in repo.index.stages if s.dvcfile.path == str(root / pipeline)}
        for name, locked in lock["stages"].items():
            stage = stages.get(name)
            if stage is None:
                continue
            if locked.get("cmd") != stage.cmd and moved_command(locked.get("cmd", "")) == stage.cmd:
                locked["cmd"] = stage.cmd
                done.append(f"{pipeline}:{name}: command recorded (its entry point renamed)")
            listed = {d.def_path: d for d in stage.deps if is_code(d.def_path)}
            old = {e["path"]: e for e in locked["deps"] if is_code(e["path"])}
            gone = [p for p in old if p not in listed]

            def today(path: str, stage=stage) -> str | None:
                return Dependency(stage, path).get_hash().value if (root / path).exists() else None

            added, kept = [], set()
            for path, dep in listed.items():
                if path in old:
                    continue
                replaced = [p for p in gone if _overlap(p, path)]
                if replaced:
                    if any(old[p].get("md5") != today(p) for p in replaced):
                        kept.update(replaced)  # what changed stays visible in the lock
                        done.append(
                            f"{pipeline}:{name}: {path} left stale (changed since the lock)"
                        )
                        continue
                    how = "unchanged since the lock"
                else:
                    now = today(path)  # hashed once, against every entry no longer listed
                    moved = next((p for p in gone if _same_file(old[p], now)), None)
                    if moved is None:
                        done.append(f"{pipeline}:{name}: {path} left new (the stage never ran it)")
                        continue
                    how = f"{moved} moved here unchanged"
                dep.save()
                saved = dep.dumpd()
                added.append({k: saved[k] for k in LOCK_KEYS if k in saved})
                done.append(f"{pipeline}:{name}: {path} recorded ({how})")
            dropped = [p for p in gone if p not in kept]
            done += [f"{pipeline}:{name}: {path} dropped (no longer listed)" for path in dropped]
            deps = [e for e in locked["deps"] if e["path"] not in dropped] + added
            locked["deps"] = sorted(deps, key=lambda e: e["path"])  # as DVC writes them
    dump_yaml(lock_path, lock)
    return done


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--check", action="store_true", help="exit 1 if any stage is out of date")
    mode.add_argument("--record", action="store_true", help="record re-expressed code in locks")
    args = parser.parse_args()
    stale = []
    for pipeline in PIPELINES:
        path = ROOT / pipeline
        if args.record:
            print("\n".join(record(pipeline)) or f"{pipeline}: nothing to record")
            continue
        text, changed = rewritten(path.read_text())
        if args.check:
            stale += [f"{pipeline}:{stage}" for stage in changed]
        elif changed:
            path.write_text(text)
            print(f"{pipeline}: {len(changed)} stages rewritten ({', '.join(changed)})")
    if stale:
        sys.exit(
            f"code deps out of date in {len(stale)} stages ({', '.join(stale[:5])}"
            f"{', ...' if len(stale) > 5 else ''}): run `uv run python scripts/dvc_deps.py`"
        )


if __name__ == "__main__":
    main()
