"""oposm command line: one command per pipeline stage, plus inspection helpers.

Each stage command loads `params.yaml`, applies `--set section.key=value` overrides for this run
only, and calls the matching `stages.<name>.run`. `dvc repro` runs the same commands (see
`dvc.yaml`). A mistake in the input is reported on one line with a non-zero exit status.
"""

from __future__ import annotations

import functools
import logging
import sys
from collections.abc import Callable
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
    Path, typer.Option("--params", "-p", help="Params file (one section per stage).")
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
    Path, typer.Option("--data", help="Data root: demos/, segments/, reports/ live under it.")
]


def _user_errors(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Turn a `UserError` into one line on stderr and exit status 1 (no traceback)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except UserError as exc:
            typer.secho(f"error: {exc}", fg=typer.colors.RED, err=True)
            raise typer.Exit(1) from None
        except KeyboardInterrupt:
            typer.secho("interrupted; no partial output was kept", err=True)
            raise typer.Exit(130) from None

    return wrapper


def _setup_logging() -> None:
    logging.basicConfig(
        level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr
    )


def _load(params: Path, overrides: list[str] | None) -> Params:
    from pipeline.config import load_params

    _setup_logging()
    return load_params(params, overrides or [])


@app.command()
@_user_errors
def ingest(
    params: ParamsOption = Path("params.yaml"),
    set_: SetOption = None,
    data: DataOption = Path("data"),
) -> None:
    """Record demonstrations into data/demos/<ingest.name>.mcap.

    With `ingest.source: maze` a scripted expert (D4RL's maze2d waypoint controller) drives a
    gymnasium-robotics PointMaze for `ingest.episodes` x `ingest.episode_steps` steps. With
    `lerobot`, `d4rl` or `minari` an existing dataset is imported (settings in `ingest.lerobot`,
    `ingest.d4rl`, `ingest.minari`), e.g. `-S ingest.source=d4rl -S ingest.d4rl.path=FILE.hdf5`.
    """
    from pipeline.paths import Paths
    from stages import ingest as stage

    stage.run(_load(params, set_), Paths(data))


@app.command()
@_user_errors
def segment(
    params: ParamsOption = Path("params.yaml"),
    set_: SetOption = None,
    data: DataOption = Path("data"),
) -> None:
    """Cut the MCAP dataset into windows of `segment.window` states, split by episode.

    Writes data/segments/<ingest.name>/ (episodes stored once + window index + train-only
    normalization statistics) and data/reports/segment.json.
    """
    from pipeline.paths import Paths
    from stages import segment as stage

    stage.run(_load(params, set_), Paths(data))


@app.command()
@_user_errors
def train(
    params: ParamsOption = Path("params.yaml"),
    set_: SetOption = None,
    data: DataOption = Path("data"),
) -> None:
    """Learn skills and the temporally abstract world model from the segments (EM, paper §2.1).

    `train.method: em` runs the paper's EM (an E-step on the posterior, then an M-step on
    policy, world model and prior, per batch); `vi` the naive joint ELBO. Keeps the best model by
    validation s_T NLL in data/models/<ingest.name>/ and resumes a killed run from its last
    state. Metrics go to data/reports/train/ (dvclive). Multi-process:
    `accelerate launch --num_processes 2 cli.py train`.
    """
    from pipeline.paths import Paths
    from stages import train as stage

    stage.run(_load(params, set_), Paths(data))


@app.command()
@_user_errors
def dynamics(
    params: ParamsOption = Path("params.yaml"),
    set_: SetOption = None,
    data: DataOption = Path("data"),
) -> None:
    """Train the single-step model p(s_t+1 | s_t, a_t), the paper's low-level baseline.

    Gaussian MLP on the train split's transitions; writes data/models/<ingest.name>-dynamics/
    and data/reports/dynamics.json. `oposm validate` compares it with the skill world model.
    """
    from pipeline.paths import Paths
    from stages import dynamics as stage

    stage.run(_load(params, set_), Paths(data))


@app.command()
@_user_errors
def validate(
    params: ParamsOption = Path("params.yaml"),
    set_: SetOption = None,
    data: DataOption = Path("data"),
) -> None:
    """Check the world model against held-out open-loop rollouts in MuJoCo (paper §4.1, fig. 4).

    From test-split start states restored exactly in the simulator, executes sequences of
    1..validate.skills skills (from the prior, and inferred from the held-out data) open loop,
    and compares where the agent ends with the TAWM's prediction and with the single-step model
    (`oposm dynamics`) rolled forward. Writes data/reports/validate.json (errors, NLL,
    calibration, wall crossings per horizon), data/reports/validate/*.csv (plots) and
    data/recordings/validate.rrd (open with `rerun`).
    """
    from pipeline.paths import Paths
    from stages import validate as stage

    stage.run(_load(params, set_), Paths(data))


@app.command()
@_user_errors
def deploy(
    params: ParamsOption = Path("params.yaml"),
    set_: SetOption = None,
    data: DataOption = Path("data"),
) -> None:
    """Plan skill sequences in MuJoCo for new goals and report success (paper §3, §4.2).

    Model-predictive control: CEM over `deploy.planner.horizon` whitened skills, rolled forward
    with the world model, for `deploy.num_envs` environments at once; the first skill runs for
    tau steps with the low-level policy, then it replans. Tasks: random_goal (goals from the
    training data), corners (D4RL's opposite corners), goal (deploy.goal). Writes
    data/reports/deploy.json (success with 95 % Wilson intervals, steps, planning latency),
    data/reports/deploy/episodes.json and data/recordings/deploy/*.rrd (`oposm view`).
    """
    from pipeline.evaluation.report import format_summary
    from pipeline.paths import Paths
    from stages import deploy as stage

    typer.echo(format_summary(stage.run(_load(params, set_), Paths(data))))


@app.command()
@_user_errors
def view(
    recordings: Annotated[
        list[Path] | None,
        typer.Argument(
            help="Recordings (.rrd) or folders of them; default data/recordings/deploy."
        ),
    ] = None,
    web: Annotated[
        bool, typer.Option(help="Serve the web viewer instead of the native one.")
    ] = False,
    dry_run: Annotated[bool, typer.Option(help="Print the rerun command, do not run it.")] = False,
) -> None:
    """Open deploy (or validate) recordings in the Rerun viewer.

    Same as `rerun data/recordings/deploy/*.rrd`; each episode is one recording, listed in the
    viewer's recording panel, laid out with the map beside the plots.
    """
    import subprocess

    files: list[Path] = []
    for path in recordings or [Path("data/recordings/deploy")]:
        found = sorted(path.glob("*.rrd")) if path.is_dir() else [path] if path.exists() else []
        if not found:
            raise UserError(f"no recordings at {path}; run `oposm deploy` first")
        files += found
    command = [sys.executable, "-m", "rerun", *(["--web-viewer"] if web else []), *map(str, files)]
    typer.echo(" ".join(command))
    if not dry_run:
        raise typer.Exit(subprocess.run(command).returncode)


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
    from pipeline.bench import bench_data as run

    for name, value in run(_load(params, set_), steps).items():
        typer.echo(f"{name:28s} {value:,.2f}")


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
    from pipeline.bench import IMPORT_SOURCES
    from pipeline.bench import bench_import as run

    chosen = tuple(source or IMPORT_SOURCES)
    unknown = sorted(set(chosen) - set(IMPORT_SOURCES))
    if unknown:
        raise UserError(f"unknown source {unknown[0]!r}; use {', '.join(IMPORT_SOURCES)}")
    for name, value in run(_load(params, set_), frames, chosen).items():
        typer.echo(f"{name:28s} {value:,.2f}")


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
    params: ParamsOption = Path("params.yaml"),
    set_: SetOption = None,
    data: DataOption = Path("data"),
) -> None:
    """EM (or VI) update steps/s and sub-trajectories/s at the train params' model size.

    Needs the segments (`oposm segment`). Compare configs with -p params-paper.yaml.
    """
    from pipeline.devices import resolve_device
    from pipeline.paths import Paths
    from pipeline.segments import load_segments
    from pipeline.training.bench import bench_train as run

    p = _load(params, set_)
    device = resolve_device(p.train.device, "train.device")
    segments = load_segments(Paths(data).segments(p.ingest.name))
    typer.echo(f"device {device}, method {p.train.method}, z {p.train.z_dim}, h {p.train.hidden}")
    for name, value in run(p.train, segments, steps, device).items():
        typer.echo(f"{name:28s} {value:,.2f}")


@bench_app.command("plan")
@_user_errors
def bench_plan(
    envs: Annotated[int, typer.Option(help="Environments planned for at once.")] = 64,
    repeats: Annotated[int, typer.Option(help="Timed one-environment replans.")] = 10,
    batch_repeats: Annotated[int, typer.Option(help="Timed batched replans.")] = 3,
    params: ParamsOption = Path("params.yaml"),
    set_: SetOption = None,
    data: DataOption = Path("data"),
) -> None:
    """Planning latency per replan (one env) and plans/s (--envs at once), for deploy.planner
    and the paper's table 14 params. Needs a trained model (`oposm train`)."""
    from pipeline.bench import bench_plan as run
    from pipeline.paths import Paths

    p = _load(params, set_)
    for name, value in run(p, Paths(data), envs, repeats, batch_repeats).items():
        typer.echo(f"{name:32s} {value:,.4f}")


expert_app = typer.Typer(
    help="Learned locomotion experts (the ant that drives OGBench-style ant-maze data).",
    no_args_is_help=True,
)
app.add_typer(expert_app, name="expert")
RobotArg = Annotated[str, typer.Argument(help="Robot: ant.")]
ExpertParamsOption = Annotated[
    Path | None, typer.Option("--params", "-p", help="Default: experts/<robot>/params.yaml.")
]


@expert_app.command("train")
@_user_errors
def expert_train(
    robot: RobotArg,
    params: ExpertParamsOption = None,
    set_: SetOption = None,
    data: DataOption = Path("data"),
    ship: Annotated[bool, typer.Option(help="Ship the finished actor to experts/<robot>/.")] = True,
) -> None:
    """SAC on OGBench's direction task; after a kill, rerun the same command to resume.

    Hours on 2 CPU cores. Checkpoints in data/experts/<robot>/; the finished actor goes to
    experts/<robot>/actor.safetensors + actor.json, checked (`oposm expert check`)."""
    from pipeline.expert_config import check_robot, default_params_path, load_expert_params
    from stages import expert as stage

    _setup_logging()
    path = params or default_params_path(check_robot(robot))
    p = load_expert_params(path, set_)
    out = stage.scratch_dir(robot, data)
    typer.echo(stage.train(p, robot, out, stage.ship_dir(robot) if ship else None, path))


@expert_app.command("check")
@_user_errors
def expert_check(
    robot: RobotArg,
    actor: Annotated[
        Path | None, typer.Option(help="Actor .safetensors (default: the shipped one).")
    ] = None,
    params: ExpertParamsOption = None,
    set_: SetOption = None,
    data: DataOption = Path("data"),
) -> None:
    """Speed along the command, and success on OGBench's maze tasks driven by the BFS oracle.

    Writes data/experts/<robot>/check.json and the actor JSON's `quality` entry."""
    from pipeline.evaluation.ant_expert import summary_lines
    from pipeline.expert_config import check_robot, default_params_path, load_expert_params
    from stages import expert as stage

    _setup_logging()
    p = load_expert_params(params or default_params_path(check_robot(robot)), set_)
    path = actor or stage.ship_dir(robot) / "actor.safetensors"
    report = stage.scratch_dir(robot, data) / "check.json"
    quality = stage.check(p, robot, path, report)
    typer.echo(f"actor {path} (step {quality['actor_steps']}); report {report}")
    typer.echo("\n".join(summary_lines(quality)))


if __name__ == "__main__":
    app()
