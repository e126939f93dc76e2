"""Rerun recordings: a writer that fails midway leaves no open stream and no file behind."""

import os
from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.evaluation.episodes import EpisodeResult
from pipeline.evaluation.tasks import EpisodeSpec
from pipeline.viz import deploy, validate


def _open_files_under(folder) -> list[str]:
    """Files this process holds open below `folder` (Linux: /proc/self/fd)."""
    found = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith(str(folder)):
            found.append(target)
    return found


def _fail(*args, **kwargs):
    raise RuntimeError("failed midway")


LAYOUT = {"bounds": [-1.0, 1.0, -1.0, 1.0], "maze_size_scaling": 1.0, "wall_cells": []}
LAYOUT.update(x_map_center=1.0, y_map_center=1.0)
SPEC = SimpleNamespace(goal_dims=(0, 1), dt=0.01, layout=LAYOUT)


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc/self/fd (Linux)")
@pytest.mark.parametrize("writer", ["deploy", "validate"])
def test_a_recording_that_fails_midway_is_closed_and_removed(tmp_path, monkeypatch, writer):
    if writer == "deploy":
        monkeypatch.setattr(deploy, "_log_agent", _fail)
        result = EpisodeResult(EpisodeSpec("goal", 0, np.zeros(4), np.ones(2), 0))

        def write():
            deploy.write_episode_recording(tmp_path / "episode.rrd", result, SPEC)
    else:
        monkeypatch.setattr(validate, "log_maze", _fail)

        def write():
            run = SimpleNamespace(starts=[0], modes={}, repeats=1)
            validate.write_recording(tmp_path / "validate.rrd", run, SPEC, 1)

    # `caught` keeps the traceback, and with it the writer's locals, alive: as in a caller that
    # is still handling the error, the stream must be closed already, not when it is collected.
    with pytest.raises(RuntimeError, match="failed midway") as caught:
        write()
    assert _open_files_under(tmp_path) == [], caught.traceback[-1]
    assert list(tmp_path.iterdir()) == []
