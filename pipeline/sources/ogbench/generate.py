"""OGBench maze datasets generated with OGBench's own recipe, for the point and the ant.

Follows `data_gen_scripts/generate_locomaze.py` of OGBench's repository (read for its facts; the
loop is written here because the script needs OGBench's training code, absl and a saved agent):

- each episode resets the real env (`terminate_at_goal=False`) with `task_info = (init_ij,
  goal_ij)`: the start cell uniform over all free cells; the goal cell uniform over the "vertex"
  cells (free cells that are not straight hallways) for `navigate` and `explore`, and uniform over
  the cells exactly 4 BFS steps from the start for `stitch`; OGBench's reset adds its +-1 noise;
- each step a unit direction: to the BFS oracle subgoal (`explore`: a random unit direction,
  redrawn every 10 steps); the action is the point's direction itself, or the ant expert's
  deterministic action for that direction (`expert.py`), plus N(0, noise^2) per dimension,
  clipped to the action bounds ([-1, 1]); noise: point 0.5, ant 0.2 (navigate, stitch), 1.0
  (explore, both);
- `navigate` draws a new vertex goal (`set_goal(goal_ij)`, with noise) whenever the current one is
  reached (within 1.0 for the point, 0.5 for the ant, after the step);
- OGBench's sizes: navigate 1000 episodes x 1001 steps (giant: 500 x 2001), stitch 5000 x 201,
  explore 10000 x 501, each plus a 10 % validation file. Here the sizes are params; the
  validation share comes from the segment stage's split instead of a second file.

OGBench draws its reset and goal noise from numpy's global generator and the ant's reset noise
from the env's: each episode runs under `global_seed` of its own seed and resets the env with
another, so a dataset is a function of the recipe (the ant expert runs on one torch thread, whose
results do not depend on the machine's thread setting). Recorded per step: the observation
(point `[x, y]`; ant `qpos + qvel`, 29), the action sent, the goal pursued, whether the step
reached it, and the exact MuJoCo state before the step (`[time, qpos, qvel]`, time on the dataset
clock; OGBench's files keep `qpos` / `qvel` of the same instant).
"""

from __future__ import annotations

from collections.abc import Iterator

import gymnasium
import mujoco
import numpy as np

from pipeline.dataset import Episode
from pipeline.devices import torch_threads
from pipeline.envs.ant import global_seed
from pipeline.envs.maze import PHYSICS_SPEC
from pipeline.envs.ogbench import make_ogbench_env
from pipeline.envs.ogbench_oracle import BFSOracle
from pipeline.sources.common import Clock, ImportedDataset, with_progress
from pipeline.sources.ogbench.expert import (
    Controller,
    ant_controller,
    load_ant_expert,
    point_controller,
)
from pipeline.sources.ogbench.info import dataset_info, ogbench_spec
from pipeline.sources.ogbench.recipe import (
    EXPLORE_EVERY,
    STITCH_CELLS,
    Recipe,
    cells_at_distance,
    maze_cells,
)


def generate_ogbench(recipe: Recipe, name: str, progress: bool = False) -> ImportedDataset:
    """The dataset `recipe` describes, as a lazy stream (see the module docstring).

    The ant expert is loaded and checked here, before any episode: a bad `recipe.expert` fails
    before a file is created. Its provenance is `info.generator["expert"]`.

    Raises:
        UserError: the ant expert is missing, unreadable or not an ant actor.
    """
    spec = ogbench_spec(recipe.env_id)
    generator = recipe.to_dict()
    controller: Controller = point_controller
    if recipe.loco == "ant":
        assert recipe.expert is not None  # make_recipe requires it
        actor, generator["expert"] = load_ant_expert(recipe.expert, spec)
        controller = ant_controller(actor)
    info = dataset_info(spec, name, recipe.seed, generator, goal_dim=2)
    frames = recipe.episodes * recipe.episode_steps
    stream = _generate(recipe, spec.dt, controller)
    return ImportedDataset(info, with_progress(stream, frames, name, progress), frames)


def _generate(recipe: Recipe, dt: float, controller: Controller) -> Iterator[Episode]:
    env = make_ogbench_env(
        recipe.env_id, terminate_at_goal=False, max_episode_steps=recipe.episode_steps
    )
    try:
        free, vertex = maze_cells(np.asarray(env.unwrapped.maze_map))
        oracle = BFSOracle(recipe.env_id)
        clock = Clock(dt)
        seeds = np.random.SeedSequence(recipe.seed).spawn(recipe.episodes)
        for k, seq in enumerate(seeds):
            rng = np.random.default_rng(seq)
            numpy_seed, action_space_seed = (int(s) for s in seq.generate_state(2))
            # The reset's settling steps sample the action space; they are reset away, but
            # seeding it keeps every draw of an episode a function of its seed.
            env.action_space.seed(action_space_seed)
            with global_seed(numpy_seed), torch_threads(1):
                arrays = _episode(env, recipe, rng, free, vertex, oracle, controller)
            time = clock.next(recipe.episode_steps)
            arrays["physics"][:, 0] = time
            yield Episode(index=k, time=time, **arrays)
    finally:
        env.close()


def _episode(
    env: gymnasium.Env,
    recipe: Recipe,
    rng: np.random.Generator,
    free: list,
    vertex: list,
    oracle: BFSOracle,
    controller: Controller,
) -> dict[str, np.ndarray]:
    """One episode of `generate_locomaze.py`'s loop."""
    maze = env.unwrapped
    maze_map = np.asarray(maze.maze_map)
    init_ij = free[rng.integers(len(free))]
    if recipe.dataset_type == "stitch":
        near = cells_at_distance(maze_map, init_ij, STITCH_CELLS)
        goal_ij = near[rng.integers(len(near))] if near else init_ij
    else:
        goal_ij = vertex[rng.integers(len(vertex))]
    ob, _ = env.reset(
        seed=int(rng.integers(2**31)),
        options={"task_info": {"init_ij": init_ij, "goal_ij": goal_ij}},
    )
    n = recipe.episode_steps
    low, high = env.action_space.low.astype(np.float64), env.action_space.high.astype(np.float64)
    physics = np.empty((n, mujoco.mj_stateSize(maze.model, PHYSICS_SPEC)))
    obs, actions = np.empty((n, ob.shape[0])), np.empty((n, low.shape[0]))
    goals, reached = np.empty((n, 2)), np.zeros(n, dtype=bool)
    direction = np.zeros(2)
    for t in range(n):
        mujoco.mj_getState(maze.model, maze.data, physics[t], PHYSICS_SPEC)
        obs[t], goals[t] = ob, maze.cur_goal_xy
        if recipe.dataset_type == "explore":
            if t % EXPLORE_EVERY == 0:
                direction = rng.standard_normal(2)
                direction /= np.linalg.norm(direction) + 1e-6
        else:
            direction = oracle.direction(maze.get_xy(), maze.cur_goal_xy)
        action = controller(ob, direction) + rng.normal(0.0, recipe.noise, low.shape[0])
        actions[t] = action = np.clip(action, low, high)
        ob, _, _, _, step_info = env.step(action)
        reached[t] = bool(step_info["success"])
        if reached[t] and recipe.dataset_type == "navigate":
            maze.set_goal(vertex[rng.integers(len(vertex))])
    return {
        "observations": obs,
        "actions": actions,
        "physics": physics,
        "goals": goals,
        "goal_reached": reached,
    }
