"""oposm command line: one command per pipeline stage, plus inspection helpers.

Each stage command loads `params.yaml`, applies `--set section.key=value` overrides for this run
only, and calls the matching `stages.<name>.run`. `dvc repro` runs the same commands (see
`dvc.yaml`). A mistake in the input is reported on one line with a non-zero exit status.
"""

from __future__ import annotations

import dataclasses
import errno
import functools
import hashlib
import importlib
import logging
import os
import re
import sys
from collections.abc import Callable
from inspect import cleandoc, signature
from pathlib import Path
from typing import Annotated, Any

import typer

from pipeline.config import Params
from pipeline.errors import UserError

app = typer.Typer(
    name="oposm",
    help=(
        "Learn skills and a temporally abstract world model from offline demonstrations, then "
        "plan with them in MuJoCo (OPOSM).\n\n"
        "Pipeline: ingest -> segment -> train -> validate -> deploy. Run it all with `dvc repro`, "
        "or one stage at a time with the commands below. Settings live in params.yaml; override "
        "one for a single run with --set, e.g. `oposm segment --set segment.window=20`."
    ),
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)

ParamsOption = Annotated[
    Path,
    typer.Option(
        "--params",
        "-p",
        help="Params file (one section per stage), or a variant: `extends: <base>` + what differs.",
    ),
]
SetOption = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        "-S",
        help="Override a param for this run: section.key=value (repeatable), "
        "e.g. -S ingest.episodes=10.",
    ),
]
DataOption = Annotated[
    Path | None,
    typer.Option(
        "--data",
        help="Data root: demos/, segments/, reports/ live under it [default: data].",
        show_default=False,
    ),
]
RunOption = Annotated[
    str | None,
    typer.Option(
        "--run",
        help="Write under data/runs/<RUN>/ (inputs the run did not make come from data/). "
        "Runs with --set or another --params get a run folder named after them anyway, so "
        "the pipeline's tracked outputs only change by `dvc repro` or a plain stage command.",
    ),
]
MetricsOption = Annotated[
    Path | None,
    typer.Option(
        "--metrics",
        help="Folder of the stage's headline metrics, <stage>.json (default: metrics/ beside "
        "the data root, or the run folder's metrics/ for a --run).",
        show_default=False,
    ),
]
ModelOption = Annotated[
    Path | None,
    typer.Option(
        "--model",
        help="Skill model folder to read instead of <data>/models/<ingest.name>/, e.g. "
        "data/models/NAME/by/st_nll_prior (the best checkpoint by another selection criterion, "
        "see train.select).",
        show_default=False,
    ),
]
PIPELINE_PARAMS = Path("params.yaml")


# Loggers whose INFO lines the CLI shows; third-party libraries only speak from WARNING up (e.g.
# `datasets` logs "JAX version ... available" at INFO on every LeRobot import).
_OUR_LOGGERS = ("pipeline", "stages", "bench", "cli")
log = logging.getLogger("cli")


def _close_progress_bars() -> None:
    """End any open tqdm bar, so that what is printed next starts on its own line."""
    std = sys.modules.get("tqdm.std")
    for bar in list(getattr(getattr(std, "tqdm", None), "_instances", ())):
        bar.close()


def _path_for_user(filename: str | os.PathLike) -> str:
    """The file a user asked for, for the hidden temporary (`.tmp-<name>.<random>`) or moved-aside
    (`.old-<name>.<pid>`) names that atomic writes use next to it, in the path's last part or in
    a folder above it (a file written into a staged output folder)."""
    parts = []
    for part in Path(filename).parts:
        while hidden := re.fullmatch(r"\.(?:tmp|old)-(.+)\.[^.]+", part):
            part = hidden.group(1)  # a temporary of a temporary: once more
        parts.append(part)
    return str(Path(*parts)) if parts else str(filename)


def _os_error_message(exc: OSError, data_option: bool = False) -> str:
    """'<path>: <why> (<what to do>)' for an `OSError` (read-only or full disk, missing
    permission, a file where a folder is needed, ...); `data_option`: the command takes --data,
    a way out to suggest."""
    why = exc.strerror or str(exc)
    if exc.filename is None:
        return why
    path = _path_for_user(exc.filename)
    elsewhere = ", or use `--data` elsewhere" if data_option else ""
    if exc.errno in (errno.ENOTDIR, errno.EEXIST):
        culprit = _file_in_the_way(Path(path))
        if culprit is not None:
            return (
                f"{path}: {why} ({culprit} is a file, and a folder is needed there; move or "
                f"delete that file{elsewhere})"
            )
    if exc.errno == errno.EISDIR:
        return f"{path}: {why} (that path is a folder, and a file is needed there; move it away)"
    if exc.errno in (errno.EACCES, errno.EPERM):
        return f"{path}: {why} (make it readable and writable for you{elsewhere})"
    if exc.errno == errno.EROFS and data_option:
        return f"{path}: {why} (use `--data` on a writable disk)"
    return f"{path}: {why}"


def _file_in_the_way(path: Path) -> Path | None:
    """The deepest existing part of `path` (itself or a folder above it) when it is not a
    folder: what a 'File exists' / 'Not a directory' error means."""
    for part in (path, *path.parents):
        if part.exists():
            return None if part.is_dir() else part
    return None


def _fail(message: str, status: int = 1) -> None:
    _close_progress_bars()
    typer.secho(message, fg=typer.colors.RED if status == 1 else None, err=True)
    raise typer.Exit(status)


# What to lower when a command runs out of GPU memory (by command function name), most
# effective first, and its device param.
_MEMORY_PARAMS: dict[str, tuple[tuple[str, ...], str]] = {
    "train": (("train.batch_size", "train.val_windows", "train.hidden"), "train.device"),
    "dynamics": (("dynamics.batch_size", "dynamics.val_transitions"), "dynamics.device"),
    "validate": (("validate.particles", "validate.starts"), "validate.device"),
    "deploy": (("deploy.num_envs", "deploy.planner.candidates"), "deploy.device"),
    "bench_train": (("train.batch_size", "train.hidden"), "train.device"),
    "bench_plan": (("--envs", "deploy.planner.candidates"), "deploy.device"),
}


def _out_of_memory(exc: BaseException) -> bool:
    """Whether `exc` is PyTorch running out of accelerator memory. Checked without importing
    torch (the CLI starts without it): if torch was never imported it cannot have raised."""
    torch = sys.modules.get("torch")
    oom = getattr(torch, "OutOfMemoryError", None)
    if isinstance(oom, type) and isinstance(exc, oom):
        return True
    text = str(exc)
    return isinstance(exc, RuntimeError) and "CUDA" in text and "out of memory" in text.lower()


def _out_of_memory_message(command: str, exc: BaseException) -> str:
    """One line: which command ran out of GPU memory, how much it asked for, what to lower."""
    asked = re.search(r"Tried to allocate [\d.]+ ?[KMGT]?i?B", str(exc))
    what = f" ({asked.group(0).replace('Tried', 'tried')})" if asked else ""
    name = f"oposm {command.replace('_', ' ')}"
    if command not in _MEMORY_PARAMS:
        return f"out of GPU memory in `{name}`{what}; lower its batch sizes, or use the CPU"
    lower, device = _MEMORY_PARAMS[command]
    return (
        f"out of GPU memory in `{name}`{what}; lower {' or '.join(lower)}, or run on the CPU "
        f"with -S {device}=cpu"
    )


def _user_errors(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Turn a `UserError`, an `OSError` or running out of GPU memory into one line on stderr and
    exit status 1 (no traceback)."""
    data_option = "data" in signature(fn).parameters

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except UserError as exc:
            _fail(f"error: {exc}")
        except OSError as exc:
            _fail(f"error: {_os_error_message(exc, data_option)}")
        except KeyboardInterrupt:
            _fail("interrupted; no partial output was kept", status=130)
        except Exception as exc:
            if not _out_of_memory(exc):
                raise
            _fail(f"error: {_out_of_memory_message(fn.__name__, exc)}")

    return wrapper


def _setup_logging() -> None:
    logging.basicConfig(
        level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr
    )
    for name in _OUR_LOGGERS:
        logging.getLogger(name).setLevel(logging.INFO)


def _end_with_dvc() -> None:
    """Under `dvc repro` / `dvc exp run`, stop when DVC is killed instead of training on as an
    orphan (Linux: the kernel sends SIGTERM when the parent dies; the resume state stays)."""
    if "DVC_STAGE" not in os.environ or not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    pr_set_pdeathsig = 1
    ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGTERM)
    if os.getppid() == 1:  # DVC died before the call above
        os.kill(os.getpid(), signal.SIGTERM)


def _load(params: Path, overrides: list[str] | None) -> Params:
    from pipeline.config import load_params

    _setup_logging()
    _end_with_dvc()
    return load_params(params, overrides or [])


def _print_numbers(numbers: dict[str, float], width: int = 28, digits: int = 2) -> None:
    for name, value in numbers.items():
        typer.echo(f"{name:{width}s} {value:,.{digits}f}")


def _deploy_summary(report: dict[str, Any]) -> str:
    from pipeline.evaluation.report import format_summary

    return format_summary(report)


def _paths(params: Path, overrides: list[str] | None, data: Path | None, run: str | None):
    """Where a stage command writes: the pipeline's `data/` (and `metrics/`) for the pipeline's
    own command (as `dvc repro` runs it: default params, no --set), else a run folder.

    An explicit `--data` root is the user's choice of where everything goes and is used as is.
    """
    from pipeline.paths import Paths

    if data is not None and run is None:
        return Paths(data)
    data = data or Path("data")
    adhoc = bool(overrides) or params.resolve() != PIPELINE_PARAMS.resolve()
    if run is None and (not adhoc or os.environ.get("DVC_STAGE")):
        return Paths(data)
    if run is None:  # the files a variant resolves from: a changed base is another run
        from pipeline.config import params_files

        text = b"".join(path.read_bytes() for path in params_files(params))
        key = hashlib.sha256(text + "\0".join(overrides or []).encode())
        run = f"adhoc-{key.hexdigest()[:8]}"
        log.info(
            "--set/--params differ from the pipeline's: this run writes under %s "
            "(--run NAME names the folder; `dvc repro` owns data/ itself)",
            data / "runs" / run,
        )
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", run):
        raise UserError(f"--run {run!r}: use letters, digits, '.', '_' and '-' only")
    return Paths.for_run(data, run)


def _stage_command(
    name: str,
    doc: str,
    announce: str | None = None,
    show: Callable[[Any], str] | None = None,
    reads_model: bool = False,
) -> None:
    """Register `oposm <name>`: load the params (with --set overrides), run `stages.<name>.run`
    on the data root, print `show(result)` if given.

    Args:
        doc: The command's help (first line: the summary in `oposm --help`).
        announce: Logged before the stage starts, for stages that are silent for a while first.
        reads_model: The stage reads the skill model: it takes `--model`.
    """

    def run_stage(params, set_, data, run, metrics, model=None) -> None:
        p = _load(params, set_)
        paths = _paths(params, set_, data, run)
        if metrics is not None:
            paths = dataclasses.replace(paths, metrics_root=metrics)
        if model is not None:
            paths = dataclasses.replace(paths, model_dir=model)
        if announce:
            log.info(announce)
        result = importlib.import_module(f"stages.{name}").run(p, paths)
        if show is not None:
            typer.echo(show(result))

    def command(
        params: ParamsOption = PIPELINE_PARAMS,
        set_: SetOption = None,
        data: DataOption = None,
        run: RunOption = None,
        metrics: MetricsOption = None,
    ) -> None:
        run_stage(params, set_, data, run, metrics)

    def command_with_model(
        params: ParamsOption = PIPELINE_PARAMS,
        set_: SetOption = None,
        data: DataOption = None,
        run: RunOption = None,
        metrics: MetricsOption = None,
        model: ModelOption = None,
    ) -> None:
        run_stage(params, set_, data, run, metrics, model)

    if reads_model:
        command = command_with_model
    command.__name__ = command.__qualname__ = name
    app.command(name, help=cleandoc(doc))(_user_errors(command))


_stage_command(
    "ingest",
    """Record demonstrations into data/demos/<ingest.name>.mcap.

    With `ingest.source: maze` a scripted expert (D4RL's maze2d waypoint controller) drives a
    gymnasium-robotics PointMaze for `ingest.episodes` x `ingest.episode_steps` steps. With
    `ogbench`, OGBench's recipe drives its point maze (`ingest.ogbench`), or its downloaded .npz
    is imported (`ingest.ogbench.path`). With `lerobot`, `d4rl` or `minari` an existing dataset
    is imported (settings in `ingest.lerobot`, `ingest.d4rl`, `ingest.minari`), e.g.
    `-S ingest.source=d4rl -S ingest.d4rl.path=FILE.hdf5`.
    """,
)
_stage_command(
    "segment",
    """Cut the MCAP dataset into windows of `segment.window` states, split by episode.

    Writes data/segments/<ingest.name>/ (episodes stored once + window index + train-only
    normalization statistics) and data/reports/segment.json.
    """,
)
_stage_command(
    "train",
    """Learn skills and the temporally abstract world model from the segments (EM, paper §2.1).

    `train.method: em` runs the paper's EM (an E-step on the posterior, then an M-step on
    policy, world model and prior, per batch); `vi` the naive joint ELBO. Keeps the best model by
    validation s_T NLL in data/models/<ingest.name>/ and resumes a killed run from its last
    state. Metrics go to data/reports/train/ (dvclive). Multi-process:
    `accelerate launch --num_processes 2 cli.py train`.
    """,
    announce="train: loading PyTorch, Accelerate, dvclive and the segments (a few seconds)",
)
_stage_command(
    "dynamics",
    """Train the single-step model p(s_t+1 | s_t, a_t), the paper's low-level baseline.

    Gaussian MLP on the train split's transitions; writes data/models/<ingest.name>-dynamics/
    and data/reports/dynamics.json. `oposm validate` compares it with the skill world model.
    """,
)
_stage_command(
    "bc",
    """Fit the Gaussian behaviour-cloning policy p(a | s): LLP's action prior (paper §4.2).

    On the train split's steps (maximum likelihood, best validation NLL kept); writes
    data/models/<ingest.name>-bc/. `deploy.agents: [llp]` plans with it and `oposm dynamics`.
    """,
)
_stage_command(
    "gcbc",
    """Fit goal-conditioned behaviour cloning p(a | s, g), OGBench's GCBC baseline.

    Goals are later states of the same episode (x-y), drawn as OGBench's GCBC draws them; writes
    data/models/<ingest.name>-gcbc/. `deploy.agents: [gcbc]` runs it closed loop.
    """,
)
_stage_command(
    "value",
    """Fit a goal-conditioned value V(s, g): the steps to a goal, for OPOSM's planning cost.

    Implicit value learning (GCIVL, OGBench's recipe: expectile regression, hindsight goals, the
    environment's success rule) on the train split; writes data/models/<ingest.name>-value/ and
    data/reports/value/report.json (held-out steps to go against the recorded ones). Used by
    `oposm deploy` when `value.weight > 0`; not part of the paper's method.
    """,
)
_stage_command(
    "validate",
    """Check the world model against held-out data, and open loop in MuJoCo (paper §4.1, fig. 4).

    On any dataset: from test-split start states, the skills of the next 1..validate.skills
    recorded windows (inferred by the posterior) are chained through the TAWM and compared with
    the recorded states, beside the single-step model (`oposm dynamics`) rolled over the recorded
    actions and no model. With a simulator, also executes sequences of skills (from the prior,
    and inferred) open loop from the restored states. Writes data/reports/validate/report.json
    (errors, NLL, calibration per horizon), data/reports/validate/*.csv (plots) and
    data/recordings/validate.rrd (`oposm view`). A robot's dataset: docs/robot.md.
    """,
    reads_model=True,
)
_stage_command(
    "deploy",
    """Run agents in MuJoCo towards new goals and report success (paper §3, §4.2, table 4).

    `oposm` (default): model-predictive control, CEM over `deploy.planner.horizon` whitened
    skills rolled forward with the world model, for `deploy.num_envs` environments at once; the
    first skill runs for tau steps with the low-level policy, then it replans. Baselines on the
    same episodes (`-S deploy.agents=[oposm,llp,gcbc,expert]`): llp (CEM over whitened actions
    with the single-step model, `oposm dynamics` + `oposm bc`), gcbc (`oposm gcbc`), expert (the
    data's scripted controller). Tasks: random_goal (goals from the training data), corners
    (D4RL's opposite corners), goal (deploy.goal). Writes data/reports/deploy/report.json
    (success with 95 % Wilson intervals, steps, planning time and FLOPs per replan, OPOSM vs
    LLP), data/reports/deploy/episodes.json and data/recordings/deploy/*.rrd (`oposm view`).
    """,
    show=_deploy_summary,
    reads_model=True,
)
_stage_command(
    "oracle",
    """Run OGBench's scripted oracles on its manipulation tasks: the reference beside the agents.

    For cube-single, cube-double and scene datasets: OGBench's plan oracles (those that make the
    play data), one subtask at a time toward each evaluation task's goal, in OGBench's own env,
    on the starts of `oposm deploy`'s episodes (`deploy.episodes` per task). Use `--run oracle`:
    writes <data>/runs/oracle/reports/deploy/report.json, in the deploy report's layout.
    """,
)


report_app = typer.Typer(
    help="Write a benchmark's results page under results/, beside the published numbers.",
    no_args_is_help=True,
)
app.add_typer(report_app, name="report")


@report_app.command("experiments")
@_user_errors
def report_experiments(
    experiments: Annotated[
        Path, typer.Option(help="The experiments' params (which mazes, mass factors).")
    ] = Path("experiments/params.yaml"),
    repo: Annotated[
        Path, typer.Option(help="The folder the experiments' data roots are relative to.")
    ] = Path("."),
    out: Annotated[Path, typer.Option(help="Folder of the report.")] = Path("results"),
) -> None:
    """The paper's experiments beside the paper's numbers: results/experiments.md.

    The last stage of `dvc repro experiments/dvc.yaml`: reads the deploy reports of the maze-size
    and mass runs, gives each claim of the paper a verdict (holds / does not hold /
    inconclusive, from 95 % intervals), and writes results/experiments.md, experiments.json and
    the plots' CSVs (`dvc plots show experiments/dvc.yaml`).
    """
    from stages.experiments_report import run

    _setup_logging()
    found = run(experiments, repo, out)
    for claim in found["claims"]:
        typer.echo(f"{claim['verdict']:>13s}  {claim['claim']}: {claim['numbers']}")
    if found["not_run"]:
        typer.echo(f"not run: {'; '.join(found['not_run'])}")
    typer.echo(f"report: {out / 'experiments.md'}")


# `oposm results`: the name of `oposm report experiments` before the benchmarks joined it (the
# committed experiments page names it), hidden from the help.
app.command("results", hidden=True)(report_experiments)


# The benchmark pages take their own command lines (`oposm report antmaze --help`): each stage
# of their DVC pipelines passes its arguments through to the page's module in stages/.
_PASS_THROUGH = {"allow_extra_args": True, "ignore_unknown_options": True}


def _report_command(benchmark: str, doc: str) -> None:
    module = f"stages.{benchmark.replace('-', '_')}_report"

    def command(ctx: typer.Context) -> None:
        main = importlib.import_module(module).main
        main(ctx.args, prog=f"oposm report {benchmark}")

    command.__name__ = f"report_{benchmark.replace('-', '_')}"
    report_app.command(benchmark, help=doc, context_settings=_PASS_THROUGH, add_help_option=False)(
        _user_errors(command)
    )


_report_command(
    "antmaze",
    "The ant mazes (results/antmaze.md): maze, figure5, table3 or page, then its arguments "
    "(`oposm report antmaze --help`).",
)
_report_command(
    "manipulation",
    "The manipulation datasets (results/manipulation.md): dataset, ladder, variant or page, then "
    "its arguments (`oposm report manipulation --help`).",
)
_report_command(
    "ogbench-point",
    "OGBench's point mazes (results/ogbench-point.md): from the DVC pipeline's vars file or from "
    "run folders (`oposm report ogbench-point --help`).",
)


@app.command()
@_user_errors
def view(
    recordings: Annotated[
        list[Path] | None,
        typer.Argument(
            help="Recordings (.rrd), folders of them, or MCAP datasets (data/demos/*.mcap); "
            "default: the newest run's recordings (data/ or data/runs/<run>/)."
        ),
    ] = None,
    web: Annotated[
        bool, typer.Option(help="Serve the web viewer instead of the native one.")
    ] = False,
    dry_run: Annotated[bool, typer.Option(help="Print the rerun command, do not run it.")] = False,
    data: DataOption = None,
) -> None:
    """Open recordings, or a dataset, in the Rerun viewer.

    Without arguments: the newest run's deploy recordings (the run overview first: every
    episode's start, goal and outcome on the maze; then one recording per episode) and its
    validate recording (figure 4), and it says which run that is. An MCAP dataset opens as a
    view of the demonstrations over the maze (written to a temporary .rrd). `--web` serves the
    viewer bundled with rerun-sdk from this machine, so it works offline.
    """
    import subprocess
    import tempfile

    from pipeline.viz.runs import OVERVIEW, given, newest_run, show_first

    selection = given(recordings) if recordings else newest_run(data or Path("data"))
    if not (web or dry_run) and _no_display():
        raise UserError(
            "no display for the native viewer (DISPLAY and WAYLAND_DISPLAY are unset); "
            "use `oposm view --web` and open the address it prints in a browser"
        )
    typer.echo(f"opening {selection.about}")
    with tempfile.TemporaryDirectory(prefix="oposm-view-") as tmp:
        files = [_dataset_view(f, Path(tmp)) if f.suffix == ".mcap" else f for f in selection.files]
        web_args = ["--web-viewer"] if web else []
        command = [sys.executable, "-m", "rerun", *web_args, *map(str, files)]
        typer.echo(" ".join(command))
        if dry_run:
            return
        with subprocess.Popen(command) as viewer:
            if not web and any(f.name == OVERVIEW for f in files):
                # The viewer shows whichever file loads first; put the run overview on screen.
                show_first(Path(OVERVIEW).stem, len(files), failed=lambda: bool(viewer.poll()))
            raise typer.Exit(viewer.wait())


def _dataset_view(mcap: Path, folder: Path) -> Path:
    """Write the Rerun view of an MCAP dataset into `folder`; say what it shows."""
    from pipeline.viz.dataset import write_dataset_view

    out = folder / f"{mcap.stem}.rrd"
    shown = write_dataset_view(mcap, out)
    if shown["episodes"] < shown["total"]:
        typer.echo(f"{mcap}: showing the first {shown['episodes']} of {shown['total']} episodes")
    return out


def _no_display() -> bool:
    """True on Linux without an X11 or Wayland display (the native viewer cannot open)."""
    has = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    return sys.platform.startswith("linux") and not has


@app.command()
@_user_errors
def inspect(
    file: Annotated[Path, typer.Argument(help="An oposm MCAP dataset (data/demos/*.mcap).")],
) -> None:
    """Print a readable summary of an MCAP dataset: episodes, steps, dims, metadata."""
    from pipeline.recording import format_summary, summarize

    typer.echo(format_summary(summarize(file)))


@app.command("params")
@_user_errors
def show_params(
    params: ParamsOption = Path("params.yaml"),
    set_: SetOption = None,
) -> None:
    """Validate params.yaml (with overrides) and print every resolved value."""
    import yaml

    typer.echo(yaml.safe_dump(_load(params, set_).model_dump(), sort_keys=False).rstrip())


@app.command("causal-example")
@_user_errors
def causal_example() -> None:
    """Appendix B: two skill models with equal ELBOs; the E-step objective and planning differ."""
    from pipeline.analysis.causal_example import format_report

    typer.echo(format_report())


bench_app = typer.Typer(
    help="Benchmarks: print throughput and memory (timing targets live here, not in tests).",
    no_args_is_help=True,
)
app.add_typer(bench_app, name="bench")


@bench_app.command("data")
@_user_errors
def bench_data(
    steps: Annotated[int, typer.Option(help="Dataset size in steps.")] = 1_000_000,
    params: ParamsOption = Path("params.yaml"),
    set_: SetOption = None,
) -> None:
    """Ingest (generate + write + check) and segment throughput, MCAP bytes/step, segment memory."""
    from bench.data import bench_data as run

    _print_numbers(run(_load(params, set_), steps))


@bench_app.command("import")
@_user_errors
def bench_import(
    frames: Annotated[int, typer.Option(help="Dataset size in frames.")] = 100_000,
    source: Annotated[
        list[str] | None,
        typer.Option(help="Source to time (repeatable): lerobot, d4rl, minari. Default: all."),
    ] = None,
    params: ParamsOption = Path("params.yaml"),
    set_: SetOption = None,
) -> None:
    """Import throughput (frames/s) per source, on data written by each source's own library."""
    from bench.data import IMPORT_SOURCES
    from bench.data import bench_import as run

    chosen = tuple(source or IMPORT_SOURCES)
    unknown = sorted(set(chosen) - set(IMPORT_SOURCES))
    if unknown:
        raise UserError(f"unknown source {unknown[0]!r}; use {', '.join(IMPORT_SOURCES)}")
    _print_numbers(run(_load(params, set_), frames, chosen))


export_app = typer.Typer(
    help="Write an oposm dataset in another format, to share it with other tools.",
    no_args_is_help=True,
)
app.add_typer(export_app, name="export")


@export_app.command("lerobot")
@_user_errors
def export_lerobot(
    file: Annotated[Path, typer.Argument(help="An oposm MCAP dataset (data/demos/*.mcap).")],
    root: Annotated[Path, typer.Argument(help="Folder to write the LeRobot dataset into.")],
    repo_id: Annotated[
        str | None, typer.Option(help="LeRobot repo id; default local/<dataset name>.")
    ] = None,
    task: Annotated[str | None, typer.Option(help="Task string of every frame.")] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing folder.")] = False,
) -> None:
    """Write FILE as a LeRobot v3.0 dataset (LeRobot's own writer) in ROOT.

    Open it with LeRobot's tools (`LeRobotDataset(repo_id, root=ROOT)`) or import it back with
    `oposm ingest -S ingest.source=lerobot -S ingest.lerobot.root=ROOT`.
    """
    from pipeline.sources import export_lerobot as export

    _setup_logging()
    summary = export(file, root, repo_id=repo_id, task=task, overwrite=overwrite, progress=True)
    typer.echo(
        f"wrote {summary.root} ({summary.repo_id}): {summary.episodes} episodes, "
        f"{summary.frames} frames at {summary.fps} fps"
    )


@bench_app.command("train")
@_user_errors
def bench_train(
    steps: Annotated[int, typer.Option(help="Timed update steps.")] = 50,
    dtypes: Annotated[
        str | None,
        typer.Option(
            help="Comma-separated train.dtype values to time one after the other, with the "
            "ratio of each to the first (e.g. float32,bfloat16); default: train.dtype."
        ),
    ] = None,
    reference: Annotated[
        bool,
        typer.Option(
            help="Also time the paper's EM step as its code runs it (bench/reference_em.py)."
        ),
    ] = True,
    params: ParamsOption = Path("params.yaml"),
    set_: SetOption = None,
    data: DataOption = Path("data"),
) -> None:
    """EM (or VI) update steps/s and sub-trajectories/s at the train params' model size, beside
    the paper's procedure (its code's EM step at the same sizes: `reference/*`).

    Needs the segments (`oposm segment`). Compare configs with -p params-paper.yaml, and
    precisions with --dtypes float32,bfloat16.
    """
    from bench.train import bench_train as run
    from bench.train import bench_train_dtypes
    from pipeline.paths import Paths

    loaded = _load(params, set_)
    if dtypes is None:
        _print_numbers(run(loaded, Paths(data), steps, reference=reference))
        return
    from typing import get_args

    from pipeline.config import TrainParams

    names = [d.strip() for d in dtypes.split(",") if d.strip()]
    allowed = get_args(TrainParams.model_fields["dtype"].annotation)  # train.dtype's values
    if not names or any(d not in allowed for d in names):
        raise UserError(
            f"--dtypes takes a comma-separated list of {' and '.join(allowed)}, got {dtypes!r}"
        )
    _print_numbers(bench_train_dtypes(loaded, Paths(data), steps, names, reference), width=36)


@bench_app.command("plan")
@_user_errors
def bench_plan(
    envs: Annotated[int, typer.Option(help="Environments planned for at once.")] = 64,
    repeats: Annotated[int, typer.Option(help="Timed one-environment replans.")] = 10,
    batch_repeats: Annotated[int, typer.Option(help="Timed batched replans.")] = 3,
    compiled: Annotated[
        bool, typer.Option(help="Also time the compiled planner (minutes to compile on CPU).")
    ] = False,
    reference_envs: Annotated[
        int | None, typer.Option(help="Environments the reference's batch is timed on.")
    ] = None,
    triton: Annotated[
        bool, typer.Option(help="Also time the planners on the fused Triton kernel (CUDA).")
    ] = False,
    params: ParamsOption = Path("params.yaml"),
    set_: SetOption = None,
    data: DataOption = Path("data"),
) -> None:
    """Planning time, FLOPs and GFLOP/s per replan: OPOSM vs the paper's procedure vs LLP.

    In one process, interleaved: one-env replans (p50/p95) and --envs at once (per env, plans/s)
    for deploy.planner and the paper's table 14, each batched (and --compiled) and as a plain
    eager reference of the paper's procedure (one environment at a time; speedups are its time
    over ours), and (--triton) on the fused kernel of `deploy.planner.kernel`; deploy.llp (the
    paper code's LLP) and LLP at its timing figure's L 400, 100 iterations; FLOPs counted by
    torch, GFLOP/s against a measured matmul roofline. Needs `oposm train` (and `oposm
    dynamics`, `oposm bc` for LLP)."""
    from bench.plan import bench_plan as run
    from pipeline.devices import resolve_device
    from pipeline.paths import Paths

    p = _load(params, set_)
    if triton and resolve_device(p.deploy.device, "deploy.device").type != "cuda":
        raise UserError("--triton needs a CUDA GPU (deploy.device resolves to cpu)")
    numbers = run(p, Paths(data), envs, repeats, batch_repeats, compiled, reference_envs, triton)
    _print_numbers(numbers, width=44, digits=4)


expert_app = typer.Typer(
    help="Learned locomotion experts (the ant that drives OGBench-style ant-maze data).",
    no_args_is_help=True,
)
app.add_typer(expert_app, name="expert")
RobotArg = Annotated[str, typer.Argument(help="Robot: ant.")]
ExpertParamsOption = Annotated[
    Path | None, typer.Option("--params", "-p", help="Default: experts/<robot>/params.yaml.")
]
ScratchOption = Annotated[
    Path | None,
    typer.Option(help="Checkpoints, logs, reports. Default: ~/.cache/oposm/experts/<robot>."),
]


@expert_app.command("train")
@_user_errors
def expert_train(
    robot: RobotArg,
    params: ExpertParamsOption = None,
    set_: SetOption = None,
    scratch: ScratchOption = None,
    ship: Annotated[bool, typer.Option(help="Ship the finished actor to experts/<robot>/.")] = True,
) -> None:
    """SAC on OGBench's direction task; after a kill, rerun the same command to resume.

    Hours on 2 CPU cores. Checkpoints in the scratch folder (outside the work tree, so that a
    later session resumes); the finished actor goes to experts/<robot>/actor.safetensors +
    actor.json, checked (`oposm expert check`)."""
    from pipeline.ant_expert.config import check_robot, default_params_path, load_expert_params
    from stages import expert as stage

    _setup_logging()
    path = params or default_params_path(check_robot(robot))
    p = load_expert_params(path, set_)
    out = scratch or stage.scratch_dir(robot)
    result = stage.train(p, robot, out, stage.ship_dir(robot) if ship else None, path)
    typer.echo("\n".join(f"{key}: {value}" for key, value in result.items() if key != "check"))
    if "check" in result:
        from pipeline.ant_expert.check import summary_lines

        typer.echo("\n".join(summary_lines(result["check"])))


@expert_app.command("check")
@_user_errors
def expert_check(
    robot: RobotArg,
    actor: Annotated[
        Path | None, typer.Option(help="Actor .safetensors (default: the shipped one).")
    ] = None,
    params: ExpertParamsOption = None,
    set_: SetOption = None,
    scratch: ScratchOption = None,
) -> None:
    """Speed along the command, and success on OGBench's maze tasks driven by the BFS oracle.

    Writes check.json in the scratch folder and the actor JSON's `quality` entry."""
    from pipeline.ant_expert.check import summary_lines
    from pipeline.ant_expert.config import check_robot, default_params_path, load_expert_params
    from stages import expert as stage

    _setup_logging()
    p = load_expert_params(params or default_params_path(check_robot(robot)), set_)
    path = actor or stage.ship_dir(robot) / "actor.safetensors"
    report = (scratch or stage.scratch_dir(robot)) / "check.json"
    quality = stage.check(p, robot, path, report)
    typer.echo(f"actor {path} (step {quality['actor_steps']}); report {report}")
    typer.echo("\n".join(summary_lines(quality)))


if __name__ == "__main__":
    app()
