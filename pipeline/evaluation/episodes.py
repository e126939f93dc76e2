"""Closed-loop evaluation episodes: many environments stepped together under one agent (skill MPC,
low-level planning, a goal-conditioned policy or the scripted expert: `pipeline.planning.agents`).

Episodes run in waves of as many as there are environment slots. All episodes of a wave start
together, so they replan at the same steps (every `replan_every`; never for an agent that does not
plan) with one batched planning call; an episode
that reaches its goal, runs out of steps or fails drops out of the batch. A failure (an exception in
one slot's simulation, a non-finite action or prediction) ends that episode only, with its error
recorded; an exception in a batched call ends the episodes in that call; the other results stay.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from pipeline.envs.batch import BatchSim
from pipeline.evaluation.goals import GoalRule
from pipeline.evaluation.tasks import EpisodeSpec
from pipeline.planning.agents import Agent

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunConfig:
    """How episodes are run and judged.

    Attributes:
        max_steps: Step limit per episode (D4RL: 300 umaze, 600 medium, 800 large).
        replan_every: Steps between replans (a skill's tau, LLP's executed actions); None: the
            agent never plans (a static policy).
        success_radius: Success = within this distance of the goal (paper, D4RL: 0.5).
        gym_radius: Also reported: gymnasium-robotics' success distance (0.45).
    """

    max_steps: int
    replan_every: int | None
    success_radius: float = 0.5
    gym_radius: float = 0.45


@dataclass
class EpisodeTrace:
    """What happened in one episode, for recordings.

    Attributes:
        states: `[n + 1, sd]` s_0 .. s_n.
        actions: `[n, ad]` the actions sent.
        replan_steps: Step index of each replan.
        plans: Per replan, `[P + 1, sd]` the predicted states of the chosen plan (the TAWM's per
            skill, or the single-step model's per action for LLP).
        plan_costs: Per replan, the plan's predicted cost.
        plan_targets: Per replan, the waypoint `[G]` the plan aimed at (`deploy.subgoals`);
            empty when the agent plans to the goal.
    """

    states: list[np.ndarray] = field(default_factory=list)
    actions: list[np.ndarray] = field(default_factory=list)
    replan_steps: list[int] = field(default_factory=list)
    plans: list[np.ndarray] = field(default_factory=list)
    plan_costs: list[float] = field(default_factory=list)
    plan_targets: list[np.ndarray] = field(default_factory=list)


@dataclass
class EpisodeResult:
    """Outcome of one episode (`to_json` leaves the trace out).

    Attributes:
        spec: The episode's task, start, goal and seed.
        steps: Steps executed.
        steps_to_goal: First step (1-based) within `success_radius` (or meeting the
            environment's own success rule: `GoalRule`), or None.
        steps_to_goal_gym: First step within `gym_radius` (the environment's own rule where it
            has one), or None.
        min_distance: Closest distance to the goal (`GoalRule.distance`: m in a maze, success
            tolerances in OGBench's manipulation envs).
        final_distance: Distance at the end.
        fell_at: First step (1-based) at which the agent had fallen (environments whose spec
            has `fallen`, the ant), or None.
        replans: Planning calls for this episode.
        plan_seconds: Wall time of its planning: its share of each batched call (call time /
            episodes planned together).
        error: What failed, or None.
        subtasks_done: Per subtask of the goal (the kitchen: `GoalRule.subtasks`), the first
            step (1-based) at which it was complete, or None; None for goals without subtasks.
        agent: The agent's name.
        trace: States, actions and plans.
    """

    spec: EpisodeSpec
    steps: int = 0
    steps_to_goal: int | None = None
    steps_to_goal_gym: int | None = None
    min_distance: float = float("inf")
    final_distance: float = float("inf")
    fell_at: int | None = None
    replans: int = 0
    plan_seconds: float = 0.0
    error: str | None = None
    subtasks_done: list[int | None] | None = None
    agent: str = ""
    trace: EpisodeTrace = field(default_factory=EpisodeTrace)

    @property
    def success(self) -> bool:
        return self.steps_to_goal is not None

    @property
    def score(self) -> float | None:
        """D4RL's kitchen score: the share of the goal's subtasks completed during the episode;
        None for goals without subtasks."""
        done = self.subtasks_done
        return None if done is None else sum(s is not None for s in done) / len(done)

    def to_json(self) -> dict:
        s = self.spec
        return {
            "agent": self.agent,
            "task": s.task,
            "episode": s.index,
            "seed": s.seed,
            "start": s.start.tolist(),
            "goal": s.goal.tolist(),
            "success": self.success,
            "success_gym": self.steps_to_goal_gym is not None,
            "steps": self.steps,
            "steps_to_goal": self.steps_to_goal,
            "steps_to_goal_gym": self.steps_to_goal_gym,
            "min_distance": self.min_distance,
            "final_distance": self.final_distance,
            "fell_at": self.fell_at,
            "replans": self.replans,
            "plan_seconds": self.plan_seconds,
            "error": self.error,
            **(
                {"subtasks_done": self.subtasks_done, "score": self.score}
                if self.subtasks_done is not None
                else {}
            ),
        }


@dataclass(frozen=True)
class PlanCall:
    """Wall time of one batched planning call and how many environments it planned for."""

    seconds: float
    envs: int


def _describe(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}".splitlines()[0]


class _Wave:
    """The state of one wave of episodes (one per slot) while it runs."""

    def __init__(self, envs: BatchSim, specs: list[EpisodeSpec]):
        self.envs = envs
        self.results = [EpisodeResult(spec) for spec in specs]
        self.goals = np.stack([s.goal for s in specs])
        self.rule = GoalRule.of_spec(envs.spec)
        rows = np.arange(len(specs))
        if any(s.physics is not None for s in specs):  # exact start states (manipulation)
            envs.set_state(np.stack([s.physics for s in specs]), rows)
        else:
            envs.reset(np.stack([s.start for s in specs]), rows)
        envs.seed_slots([s.seed for s in specs], rows)  # used when the env has pushes
        self.states = envs.observe(rows)
        if self.rule.subtasks is not None:  # the kitchen: each subtask's first completion
            k = self.rule.subtasks(self.states[:1], self.goals[:1]).shape[-1]
            for r in self.results:  # the start is not judged (nor is it by the env)
                r.subtasks_done = [None] * k
        self.alive = np.ones(len(specs), dtype=bool)
        for i in rows:
            self.results[i].trace.states.append(self.states[i].copy())

    def fail(self, rows: np.ndarray, message: str) -> None:
        for i in rows:
            if self.alive[i]:
                log.warning("episode %s/%d failed: %s", *self._name(i), message)
                self.results[i].error = message
                self.alive[i] = False

    def _name(self, i: int) -> tuple[str, int]:
        return self.results[i].spec.task, self.results[i].spec.index


def _replan(agent: Agent, wave: _Wave, rows: np.ndarray, t: int, calls: list[PlanCall]) -> None:
    started = time.perf_counter()
    plan = agent.replan(rows, wave.states[rows])
    if plan.states.device.type == "cuda":
        torch.cuda.synchronize()
    calls.append(PlanCall(time.perf_counter() - started, len(rows)))
    share = calls[-1].seconds / len(rows)
    predicted = plan.states.double().cpu().numpy()
    costs = plan.cost.double().cpu().numpy()
    finite = np.isfinite(costs) & np.isfinite(predicted).all(axis=(1, 2))
    targets = getattr(agent, "targets", None)  # waypoints of an MPC with subgoals
    targets = None if targets is None else targets.double().cpu().numpy()
    for j, i in enumerate(rows):
        result = wave.results[i]
        result.replans += 1
        result.plan_seconds += share
        result.trace.replan_steps.append(t)
        result.trace.plans.append(predicted[j])
        result.trace.plan_costs.append(float(costs[j]))
        if targets is not None:
            result.trace.plan_targets.append(targets[j])
    wave.fail(rows[~finite], "the world model predicted non-finite states for every candidate")


def _step(wave: _Wave, rows: np.ndarray, actions: np.ndarray, t: int, cfg: RunConfig) -> None:
    failed = wave.envs.step(actions, rows)  # one slot's failure does not end the others' episodes
    for i, message in failed.items():
        wave.fail(np.array([i]), message)
    stepped = np.array([i not in failed for i in rows], dtype=bool)
    wave.states[rows[stepped]] = wave.envs.observe(rows[stepped])
    rule = wave.rule
    fallen_of = getattr(wave.envs.spec, "fallen", None)  # the ant: torso down or upside down
    fallen = np.zeros(len(rows), dtype=bool) if fallen_of is None else fallen_of(wave.states[rows])
    for j, i in enumerate(rows):
        if not stepped[j]:
            continue
        result = wave.results[i]
        result.steps = t + 1
        if fallen[j] and result.fell_at is None:
            result.fell_at = t + 1
        result.trace.actions.append(actions[j].copy())
        result.trace.states.append(wave.states[i].copy())
        state, goal = wave.states[i], wave.goals[i]
        d = rule.distance(state, goal)
        result.final_distance = d
        result.min_distance = min(result.min_distance, d)
        if rule.subtasks is not None:  # every subtask complete at some step (D4RL's rule)
            done = result.subtasks_done
            for k, now in enumerate(rule.subtasks(state, goal)):
                if now and done[k] is None:
                    done[k] = t + 1
            if result.steps_to_goal is None and all(s is not None for s in done):
                result.steps_to_goal = result.steps_to_goal_gym = t + 1
        else:
            if result.steps_to_goal is None and rule.success(state, goal, d, cfg.success_radius):
                result.steps_to_goal = t + 1
            if result.steps_to_goal_gym is None and rule.success(state, goal, d, cfg.gym_radius):
                result.steps_to_goal_gym = t + 1
        if result.steps_to_goal is not None and result.steps_to_goal_gym is not None:
            wave.alive[i] = False


def run_wave(
    agent: Agent, envs: BatchSim, specs: list[EpisodeSpec], cfg: RunConfig
) -> tuple[list[EpisodeResult], list[PlanCall]]:
    """Run `len(specs) <= len(envs)` episodes together until each ends.

    An episode ends when it is within both radii of its goal, at `cfg.max_steps`, or on failure.
    """
    wave = _Wave(envs, specs)
    agent.reset(wave.goals, [s.seed for s in specs])
    calls: list[PlanCall] = []
    for t in range(cfg.max_steps):
        rows = np.flatnonzero(wave.alive)
        if rows.size == 0:
            break
        try:
            if cfg.replan_every is not None and t % cfg.replan_every == 0:
                _replan(agent, wave, rows, t, calls)
                rows = np.flatnonzero(wave.alive)
            actions = agent.act(rows, wave.states[rows])
        except Exception as exc:  # a batched call failed: these episodes end, results stay
            wave.fail(rows, _describe(exc))
            continue
        _step(wave, rows, actions, t, cfg)
    return wave.results, calls


def run_episodes(
    agent: Agent,
    envs: BatchSim,
    specs: list[EpisodeSpec],
    cfg: RunConfig,
    on_wave: Callable[[list[EpisodeResult]], None] | None = None,
) -> tuple[list[EpisodeResult], list[PlanCall]]:
    """Run all `specs` in waves of `len(envs)`; call `on_wave` with each wave's results."""
    results: list[EpisodeResult] = []
    calls: list[PlanCall] = []
    for start in range(0, len(specs), len(envs)):
        wave_results, wave_calls = run_wave(agent, envs, specs[start : start + len(envs)], cfg)
        for r in wave_results:
            r.agent = getattr(agent, "name", "")
        results += wave_results
        calls += wave_calls
        if on_wave is not None:
            on_wave(wave_results)
    return results, calls
