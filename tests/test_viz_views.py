"""The Rerun views: the maze the right way up, what each recording holds, the layouts they carry,
that `rerun rrd verify` loads them, and what `oposm view` opens. (What they look like is checked by
eye: scripts/screenshots.py.)"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from factories import make_episodes, make_info
from rerun.chunk import RrdReader
from typer.testing import CliRunner

from cli import app
from pipeline.envs.spec import make_env_spec
from pipeline.evaluation.episodes import EpisodeResult, EpisodeTrace
from pipeline.evaluation.open_loop import ModeResult, OpenLoopResult
from pipeline.evaluation.tasks import EpisodeSpec
from pipeline.recording import write_dataset
from pipeline.viz import maze, runs
from pipeline.viz.dataset import write_dataset_view
from pipeline.viz.deploy import write_episode_recording
from pipeline.viz.overview import write_overview
from pipeline.viz.validate import write_recording

runner = CliRunner()


@pytest.fixture(scope="module")
def env():
    return make_env_spec("PointMaze_Medium-v3")


def _values(path: Path, entity: str, component: str) -> list:
    """Every row of one component of one entity (static and temporal), in file order."""
    out = []
    for chunk in RrdReader(path).store().stream():
        if chunk.entity_path == entity:
            columns = chunk.to_record_batch().to_pydict()
            out += next((v for k, v in columns.items() if k.endswith(component)), [])
    return out


def _entities(path: Path) -> set[str]:
    return set(RrdReader(path).store().schema().entity_paths())


def _views(path: Path) -> dict[str, str]:
    """Blueprint view name -> view class, from the layout the file carries."""
    reader = RrdReader(path)
    (entry,) = reader.blueprints()
    views: dict[str, dict[str, str]] = {}
    for chunk in reader.store(store=entry).stream():
        columns = chunk.to_record_batch().to_pydict()
        for key, value in columns.items():
            if key.endswith(("display_name", "class_identifier")) and value and value[0]:
                views.setdefault(chunk.entity_path, {})[key.split(":")[-1]] = value[0][0]
    return {v["display_name"]: v["class_identifier"] for v in views.values() if len(v) == 2}


def _verify(*paths: Path) -> None:
    """`rerun rrd verify`: the installed Rerun loads and interprets every file."""
    import rerun_cli  # the rerun binary itself: `python -m rerun` imports the SDK first (5 s)

    binary = Path(rerun_cli.__file__).parent / "rerun"
    result = subprocess.run(
        [str(binary), "rrd", "verify", *map(str, paths)],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stderr[-2000:]


def _result(agent: str, task: str, index: int, success: bool, plans: bool = True):
    """A short synthetic episode from Medium cell (1, 1), world (-2.5, 2.5), heading right."""
    start = np.array([-2.5, 2.5, 0.0, 0.0])
    goal = np.array([-1.5, 2.5]) if success else np.array([2.5, -2.5])
    states = [start + [0.02 * t, 0.0, 2.0, 0.0] for t in range(21)]
    trace = EpisodeTrace(states=states, actions=[np.array([0.5, -0.1])] * 20)
    if plans:
        trace.replan_steps = [0, 10]
        ahead = np.array([[0.3 * k, 0, 0, 0] for k in range(4)])
        trace.plans = [states[t] + ahead for t in (0, 10)]
        trace.plan_costs = [1.2, 0.8]
    result = EpisodeResult(EpisodeSpec(task, index, start, goal, 7 + index), agent=agent)
    result.steps, result.replans, result.trace = 20, len(trace.plans), trace
    result.steps_to_goal = 18 if success else None
    result.min_distance = result.final_distance = 0.4 if success else 4.0
    return result


def test_a_known_cell_lands_top_left_and_walls_are_solid(tmp_path, env):
    """Medium cell (1, 1), world (-2.5, 2.5), is top-left: Rerun's 2D views put y downward."""
    view = maze.to_view([-2.5, 2.5])
    assert view[0] < 0 and view[1] < 0  # left of and above the maze centre on screen
    assert np.allclose(maze.to_view([[1.0, -2.0]]), [[1.0, 2.0]])
    path = tmp_path / "episode.rrd"
    write_episode_recording(path, _result("oposm", "corners", 0, True), env)
    # The map image: pixel (col, row) covers view positions translation + scale * (col, row).
    ((translation,),) = _values(path, "/maze/walls", "translation")
    ((scale,),) = _values(path, "/maze/walls", "scale")
    image = maze.maze_image(env.layout)
    for (row, col), world in (((1, 1), [-2.5, 2.5]), ((1, 3), [-0.5, 2.5]), ((6, 6), [2.5, -2.5])):
        pixel_centre = np.array(translation[:2]) + np.array(scale[:2]) * [col + 0.5, row + 0.5]
        assert np.allclose(pixel_centre, maze.to_view(world))
    assert tuple(image[1, 1]) == maze.FLOOR and tuple(image[1, 3]) == maze.WALL  # (1, 3): a wall
    assert tuple(image[0, 0]) == maze.WALL and image.shape == (8, 8, 3)
    (start,) = _values(path, "/task/start", "positions")
    assert np.allclose(start, [maze.to_view([-2.5, 2.5])])


def test_an_episode_recording_has_outcome_legend_plans_and_linked_plots(tmp_path, env):
    path = tmp_path / "oposm-corners-0003.rrd"
    result = _result("oposm", "corners", 3, False)
    write_episode_recording(path, result, env)
    _verify(path)
    (entry,) = RrdReader(path).recordings()
    assert entry.application_id == "oposm-deploy-oposm"
    assert entry.recording_id == "oposm-corners-0003"
    entities = _entities(path)
    for entity in (
        "/maze/walls", "/legend/0", "/task/start", "/task/goal_region", "/agent/position",
        "/agent/path", "/plan/states", "/plan/earlier", "/metrics/plan_cost", "/summary",
    ):  # fmt: skip
        assert entity in entities, entity
    ((text,),) = _values(path, "/summary", "text")
    assert text.startswith("### did not reach the goal in 20 steps") and "seed 10" in text
    assert len(_values(path, "/plan/states", "positions")) == 2  # one row per replan
    assert len(_values(path, "/metrics/plan_cost", "scalars")) == 2  # points at replans
    assert len(_values(path, "/agent/position", "positions")) == 21  # every state
    assert _views(path) == {
        "maze": "2D", "outcome": "TextDocument", "distance to goal (m)": "TimeSeries",
        "plan cost at each replan": "TimeSeries", "actions": "TimeSeries",
    }  # fmt: skip
    # An agent that does not plan: no plan entities, no plan plot, its own layout.
    still = tmp_path / "gcbc-corners-0000.rrd"
    write_episode_recording(still, _result("gcbc", "corners", 0, True, plans=False), env)
    assert not any(e.startswith("/plan") for e in _entities(still))
    assert "plan cost at each replan" not in _views(still)
    assert RrdReader(still).recordings()[0].application_id == "oposm-deploy-gcbc"


def test_the_overview_takes_any_agents_results(tmp_path, env):
    results = [
        _result("oposm", "corners", 0, True), _result("oposm", "corners", 1, False),
        _result("oposm", "random_goal", 0, True), _result("llp", "corners", 0, False),
        _result("llp", "corners", 1, False),
    ]  # fmt: skip
    path = tmp_path / "overview.rrd"
    write_overview(path, results, env)
    _verify(path)
    entities = _entities(path)
    for entity in (
        "/agents/oposm/corners/starts", "/agents/oposm/corners/goals",
        "/agents/oposm/corners/failed_ends", "/agents/oposm/random_goal/starts",
        "/agents/llp/corners/failed_paths", "/success/oposm/counts", "/success/llp/counts",
        "/summary",
    ):  # fmt: skip
        assert entity in entities, entity
    assert "/agents/oposm/random_goal/failed_ends" not in entities  # no failure there
    # Where each failure ended, labelled with its task and episode.
    labels = _values(path, "/agents/llp/corners/failed_ends", "labels")[0]
    assert labels[:2] == ["corners 0", "corners 1"]
    ends = _values(path, "/agents/llp/corners/failed_ends", "strips")[0]
    assert np.allclose(np.mean(ends[0], axis=0), maze.to_view([-2.1, 2.5]))  # the last state
    # Success per task: oposm 1/2 corners, 1/1 random_goal; llp 0/2 corners.
    # (bars: `/success/<agent>/<task number>`, scaled to their rate of the 0..100 % gridlines)
    full = np.ptp(np.array(_values(path, "/success/grid", "strips")[0])[:, 0, 1])
    for agent, bars in (("oposm", {0: 0.5, 1: 1.0}), ("llp", {})):
        for task, rate in bars.items():
            ((scale,),) = _values(path, f"/success/{agent}/{task}", "scale")
            assert np.isclose(2 * scale[1], rate * full)  # 2 pixels high
    assert "/success/llp/0" not in entities  # 0 %: no bar, its count "0/2" instead
    assert _values(path, "/success/llp/counts", "labels")[0] == ["0/2"]
    assert _values(path, "/success/tasks", "labels")[0] == ["corners", "random_goal"]
    ((text,),) = _values(path, "/summary", "text")
    assert "| oposm | corners | 1/2 (50 %) |" in text and "| llp | corners | 0/2 (0 %) |" in text
    views = _views(path)
    assert views["oposm: 2/3 reached the goal"] == "2D" and views["llp: 0/2 reached the goal"]
    assert views["success rate per task"] == "2D"
    assert RrdReader(path).recordings()[0].application_id == "oposm-deploy-overview"
    write_overview(tmp_path / "none.rrd", [], env)
    assert not (tmp_path / "none.rrd").exists()


def _open_loop(layout) -> OpenLoopResult:
    """Two starts x two repeats, two skills of five steps; rollout 1's single-step prediction
    walks right through walls and out of the maze."""
    steps = 11
    line = np.linspace(0, 1, steps)[:, None]
    real = np.zeros((4, steps, 4))
    real[..., :2] = [-2.5, 2.5] + line * [1.0, 0.0]
    single = real.copy()
    single[1, :, :2] = [-2.5, 2.5] + line * [8.0, 0.0]  # x from -2.5 to 5.5: beyond 4.0
    ends = real[:, 5::5]
    mode = ModeResult(real, np.zeros((4, 10, 2)), ends, ends, np.full_like(ends, 0.1), single)
    return OpenLoopResult(5, np.array([3, 9]), 2, {"prior": mode, "posterior": mode}, 40, 0.1)


def test_validate_clips_the_single_step_model_and_plays_markers(tmp_path, env):
    path = tmp_path / "validate.rrd"
    write_recording(path, _open_loop(env.layout), env, 2)
    _verify(path)
    entities = _entities(path)
    for entity in (
        "/maze/walls", "/legend/0", "/about", "/prior/start_0/real", "/prior/start_0/real_ends",
        "/prior/start_0/single_step", "/prior/start_0/single_step_wall",
        "/posterior/start_0/tawm/sigma2", "/prior/start_1/now/real", "/prior/start_0/now/tawm",
    ):  # fmt: skip
        assert entity in entities, entity
    strips = _values(path, "/prior/start_0/single_step", "strips")[0]
    xmax = env.layout["bounds"][1]
    assert len(strips[0]) == 11 and max(p[0] for p in strips[1]) <= xmax  # cut at the border
    assert len(strips[1]) < 11
    (sigma,) = _values(path, "/prior/start_0/tawm/sigma2", "half_sizes")
    assert len(sigma) == 2 and np.allclose(sigma, 0.2)  # 2 sigma, one per skill end
    # The moving markers have a size, and the current skill's ellipse follows the time cursor.
    assert np.allclose(_values(path, "/prior/start_0/now/real", "radii")[0], [0.08])
    centres = _values(path, "/prior/start_0/now/tawm", "centers")
    assert len(centres) == 11 and centres[1] == centres[5] != centres[6]
    views = _views(path)
    assert len([v for v in views.values() if v == "2D"]) == 5  # 2 modes x 2 starts + legend
    assert any(name.startswith("prior 0 · TAWM") for name in views)


def test_the_dataset_view_shows_paths_goals_and_actions(tmp_path):
    mcap = tmp_path / "demos.mcap"
    episodes = make_episodes([30, 20])
    episodes[0].goal_reached[:] = False
    episodes[0].goal_reached[[5, 12]] = True
    write_dataset(mcap, make_info(), episodes)
    path = tmp_path / "demos.rrd"
    assert write_dataset_view(mcap, path, max_episodes=1) == {"episodes": 1, "total": 2}
    _verify(path)
    entities = _entities(path)
    for entity in (
        "/maze/walls", "/demos/paths", "/demos/agent", "/demos/current", "/demos/goal",
        "/demos/goals_reached", "/actions/fx", "/state/vx", "/summary",
    ):  # fmt: skip
        assert entity in entities, entity
    assert len(_values(path, "/demos/goals_reached", "positions")[0]) == 2
    assert len(_values(path, "/actions/fy", "scalars")) == 30  # the first episode only
    timelines = {c.name for c in RrdReader(path).store().schema().index_columns()}
    assert {"time", "episode"} <= timelines
    ((text,),) = _values(path, "/summary", "text")
    assert "episodes    2" in text and "first 1 of 2" in text
    # Without a simulator here: no maze, positions still drawn.
    foreign = make_info("robot")
    foreign.env_id = ""
    write_dataset(tmp_path / "robot.mcap", foreign, make_episodes([10]))
    write_dataset_view(tmp_path / "robot.mcap", tmp_path / "robot.rrd")
    assert "/maze/walls" not in _entities(tmp_path / "robot.rrd")


def _touch(path: Path, mtime: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")
    os.utime(path, (mtime, mtime))


def test_view_opens_the_newest_run_and_says_which(tmp_path):
    data = tmp_path / "data"
    _touch(data / "recordings/deploy/oposm-corners-0000.rrd", 1_000)
    _touch(data / "recordings/validate.rrd", 1_000)
    newer = data / "runs/big/recordings/deploy"
    for name in ("overview.rrd", "oposm-corners-0000.rrd", "oposm-corners-0001.rrd"):
        _touch(newer / name, 2_000)
    result = runner.invoke(app, ["view", "--data", str(data), "--dry-run"])
    assert result.exit_code == 0, result.output
    said, command = result.output.splitlines()[:2]
    assert said.startswith(f"opening {data / 'runs/big'} (written ")
    assert "newest of 2 runs): run overview, 2 recordings" in said
    files = command.split()[3:]
    assert files[-1].endswith("overview.rrd") and len(files) == 3  # the viewer shows it first
    web = runner.invoke(app, ["view", str(newer), "--web", "--dry-run"])
    assert "-m rerun --web-viewer" in web.output and "http" not in web.output  # served locally
    empty = runner.invoke(app, ["view", "--data", str(tmp_path / "none"), "--dry-run"])
    assert empty.exit_code == 1 and "run `oposm deploy`" in empty.output


def test_view_of_a_dataset_converts_it_for_the_viewer(tmp_path, monkeypatch):
    mcap = tmp_path / "demos.mcap"
    write_dataset(mcap, make_info(), make_episodes([15]))
    seen: list[list[str]] = []

    class Viewer:  # stands in for the viewer process; the view exists while it runs
        def __init__(self, command):
            seen.append(command)
            assert Path(command[-1]).stat().st_size > 0
            self.returncode = 0

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def wait(self):
            return 0

    monkeypatch.setattr(subprocess, "Popen", Viewer)
    monkeypatch.setenv("DISPLAY", ":0")
    result = runner.invoke(app, ["view", str(mcap)])
    assert result.exit_code == 0, result.output
    assert result.output.startswith(f"opening dataset {mcap}")
    (command,) = seen
    assert command[-1].endswith("demos.rrd") and not Path(command[-1]).exists()  # temporary


def test_show_first_puts_the_overview_on_screen(monkeypatch):
    from types import SimpleNamespace

    import rerun.experimental

    located: list[str] = []
    recordings = [
        SimpleNamespace(store_id="Recording:a:oposm-corners-0000", location="about:episode"),
        SimpleNamespace(store_id="Recording:b:overview", location="about:overview"),
    ]

    class Client:
        @classmethod
        def connect(cls):
            return cls()

        def get_state(self):
            return SimpleNamespace(recordings=recordings, loading=[])

        def set_location(self, location):
            located.append(location)

    monkeypatch.setattr(rerun.experimental, "ViewerClient", Client)
    assert runs.show_first("overview", expected=2, timeout=5)
    assert located == ["about:overview"]
    assert not runs.show_first("overview", expected=3, timeout=5, failed=lambda: True)


def test_a_recording_shows_the_waypoint_each_plan_aimed_at(tmp_path, env):
    """`deploy.subgoals`: each replan's waypoint is drawn where it is, labelled."""
    result = _result("oposm", "corners", 4, False)
    result.trace.plan_targets = [np.array([-1.5, 1.5]), np.array([-0.5, 0.5])]
    path = tmp_path / "waypoints.rrd"
    write_episode_recording(path, result, env)
    _verify(path)
    positions = _values(path, "/plan/waypoint", "positions")
    assert np.allclose(np.concatenate(positions), maze.to_view(result.trace.plan_targets))
    labels = [v for k in range(8) for v in _values(path, f"/legend/{k}/label", "labels")]
    assert ["waypoint (subgoals)"] in labels
    plain = tmp_path / "plain.rrd"
    write_episode_recording(plain, _result("oposm", "corners", 5, False), env)
    assert "/plan/waypoint" not in _entities(plain)
