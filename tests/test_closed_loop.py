"""Closed loop with a known-good controller: the scripted maze expert that generated the training
data, driven through deploy's episode runner, must reach (nearly) every goal. This checks the
runner's wiring (starts, goals, action application, success distance, early stop) independently of
any learned model, so a deploy success rate near 0 can be blamed on the model, not the harness."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from pipeline.envs.batch import BatchSim
from pipeline.envs.maze.env import make_maze_env, maze_layout
from pipeline.envs.maze.expert import ExpertConfig, WaypointExpert
from pipeline.envs.spec import PointMazeSpec
from pipeline.evaluation.episodes import RunConfig, run_episodes
from pipeline.evaluation.tasks import MazeTasks

ENV_ID = "PointMaze_Medium-v3"


class ExpertAgent:
    """The scripted expert behind the runner's agent interface (`reset`, `replan`, `act`).

    One `WaypointExpert` per slot, steering to the episode's goal (not a random one: `update`,
    which would draw a new goal, is never called). The expert plans its path once, from the start
    cell, at the episode's first replan; later replans keep it. `replan` returns what the runner
    records: the current state as a one-state "plan" with zero cost.
    """

    def __init__(self, layout, config: ExpertConfig):
        self.layout, self.config = layout, config
        self.experts: list[WaypointExpert] = []
        self.planned = np.zeros(0, dtype=bool)

    def reset(self, goals: np.ndarray, seeds) -> None:
        self.experts = [
            WaypointExpert(self.layout, self.config, np.random.default_rng(int(s))) for s in seeds
        ]
        for expert, (gx, gy) in zip(self.experts, goals, strict=True):
            expert.goal_cell = expert.cell_of(float(gx), float(gy))
            expert.goal_x, expert.goal_y = float(gx), float(gy)
        self.planned = np.zeros(len(seeds), dtype=bool)

    def replan(self, rows: np.ndarray, states: np.ndarray) -> SimpleNamespace:
        for i, s in zip(rows, states, strict=True):
            if not self.planned[i]:
                expert = self.experts[i]
                # No public "plan to this goal" in WaypointExpert: `new_goal` draws a random one.
                expert._plan(expert.cell_of(float(s[0]), float(s[1])))
                self.planned[i] = True
        return SimpleNamespace(
            states=torch.as_tensor(states, dtype=torch.float64)[:, None],
            cost=torch.zeros(len(rows), dtype=torch.float64),
        )

    def act(self, rows: np.ndarray, states: np.ndarray) -> np.ndarray:
        return np.array(
            [self.experts[i].act(*map(float, s[:4])) for i, s in zip(rows, states, strict=True)]
        )


@pytest.fixture(scope="module")
def layout():
    return maze_layout(make_maze_env(ENV_ID))


def test_the_scripted_expert_reaches_its_goals_through_the_episode_runner(layout):
    centers = np.asarray(layout["free_cell_centers"], dtype=np.float64)
    goal_pool = centers + np.random.default_rng(0).uniform(-0.25, 0.25, centers.shape)
    tasks = MazeTasks(layout, goal_pool, seed=0)
    specs = tasks.episodes("corners", 2) + tasks.episodes("random_goal", 10)
    agent = ExpertAgent(layout, ExpertConfig())  # D4RL's gains and its action noise (0.5)
    cfg = RunConfig(max_steps=600, replan_every=10)  # D4RL's medium-maze step limit

    results, calls = run_episodes(agent, BatchSim(PointMazeSpec.create(ENV_ID), 4), specs, cfg)

    assert all(r.error is None for r in results)
    assert all(r.success for r in results), [r.to_json() for r in results if not r.success]
    for r in results:
        # The runner measured the distance from its own trace, and stopped at the goal.
        final = np.linalg.norm(r.trace.states[-1][:2] - r.spec.goal)
        assert r.final_distance == pytest.approx(final) and final <= cfg.gym_radius
        assert r.steps_to_goal <= r.steps < cfg.max_steps
        assert len(r.trace.actions) == r.steps and len(r.trace.states) == r.steps + 1
        assert r.replans == len(range(0, r.steps, cfg.replan_every))
        np.testing.assert_allclose(r.trace.states[0], r.spec.start)
    # Corners: a long way (six cells), so most of an episode's budget, but far under the limit.
    assert [c.envs for c in calls][:1] == [4]
    assert min(r.steps for r in results[:2]) > 100
