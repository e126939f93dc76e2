"""What `oposm view` opens: the newest run's deploy recordings, folders of them, or datasets.

A run is the pipeline's own data root (`data/`) or an ad-hoc run folder (`data/runs/<run>/`); its
deploy recordings are `recordings/deploy/*.rrd` (the run overview first) and its figure 4 is
`recordings/validate.rrd`. The newest run is the one whose recordings were written last.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import UserError

OVERVIEW = "overview.rrd"


@dataclass(frozen=True)
class Selection:
    """Recordings to open and a line saying what they are."""

    files: list[Path]
    about: str


def recordings_in(folder: Path) -> list[Path]:
    """The `.rrd` files of a folder, the run overview last (the viewer shows the one it loads
    last)."""
    return sorted(folder.glob("*.rrd"), key=lambda p: (p.name == OVERVIEW, p.name))


def run_roots(data: Path) -> list[Path]:
    """`data` and every `data/runs/<run>` that holds recordings."""
    roots = [data, *sorted(p for p in (data / "runs").glob("*") if p.is_dir())]
    return [r for r in roots if _recordings(r)]


def _recordings(root: Path) -> list[Path]:
    validate = root / "recordings" / "validate.rrd"
    return ([validate] if validate.exists() else []) + recordings_in(root / "recordings" / "deploy")


def newest_run(data: Path) -> Selection:
    """The recordings of the run under `data` written last: validate's, then deploy's.

    Raises:
        UserError: no run under `data` has recordings.
    """
    roots = run_roots(data)
    if not roots:
        raise UserError(
            f"no recordings in {data}/recordings or {data}/runs/*/recordings; run "
            "`oposm deploy` (or `oposm validate`) first"
        )
    newest = max(roots, key=lambda r: max(f.stat().st_mtime for f in _recordings(r)))
    files = _recordings(newest)
    written = dt.datetime.fromtimestamp(max(f.stat().st_mtime for f in files))
    others = f", newest of {len(roots)} runs" if len(roots) > 1 else ""
    return Selection(files, f"{newest} (written {written:%Y-%m-%d %H:%M}{others}): {_what(files)}")


def _what(files: list[Path]) -> str:
    """E.g. "run overview, 20 episode recordings, validate (figure 4)"."""
    parts = [f"dataset {f}" for f in files if f.suffix == ".mcap"]
    names = [f.name for f in files if f.suffix != ".mcap"]
    if OVERVIEW in names:
        parts.insert(0, "run overview")
    episodes = sum(n not in (OVERVIEW, "validate.rrd") for n in names)
    if episodes:
        parts.append(f"{episodes} recording{'s' * (episodes != 1)}")
    if "validate.rrd" in names:
        parts.append("validate (figure 4)")
    return ", ".join(parts)


def given(paths: list[Path]) -> Selection:
    """Recordings named on the command line: `.rrd` / `.rbl` files, folders of `.rrd` files, or
    MCAP datasets (returned as they are: the caller converts them).

    Raises:
        UserError: a path that does not exist or a folder without recordings.
    """
    files: list[Path] = []
    for path in paths:
        if path.is_dir():
            found = recordings_in(path)
            if not found:
                raise UserError(f"no recordings (.rrd) in {path}; run `oposm deploy` first")
            files += found
        elif path.exists():
            files.append(path)
        else:
            raise UserError(f"no such file or folder: {path}")
    return Selection(files, _what(files))


def show_first(
    recording_id: str, expected: int, timeout: float = 30.0, failed: Callable[[], bool] = bool
) -> bool:
    """Best effort: once the native viewer that `rerun <files>` started (its gRPC server on the
    default port) has loaded `expected` recordings, put recording `recording_id` on screen. (It
    loads files in parallel and shows whichever finished first.) False where it could not: no
    viewer answered, another one holds the port, or the API changed (it is experimental);
    it stops waiting as soon as `failed()` says the viewer process has failed.
    """
    import time

    try:
        from rerun.experimental import ViewerClient
    except ImportError:
        return False
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not failed():
        try:
            state = ViewerClient.connect().get_state()
            found = [r for r in state.recordings if r.store_id.endswith(f":{recording_id}")]
            if found and len(state.recordings) >= expected and not state.loading:
                ViewerClient.connect().set_location(found[0].location)
                return True
        except Exception:  # not up yet, or not a viewer we can drive: keep trying, then give up
            pass
        time.sleep(0.5)
    return False
