"""Typed params of the learned locomotion experts (`oposm expert train|check ROBOT`).

The expert has its own params file next to the weights it produces (`experts/<robot>/params.yaml`),
not a section of `params.yaml`: the main job never retrains it, and the file that produced a
shipped actor stays beside it. It loads as `params.yaml` does (`pipeline.config.load_model_file`):
a variant may overlay it (`extends: params.yaml`, only the keys that differ), unknown keys and bad
values are errors that name the key, and `section.key=value` overrides apply for one run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator

from pipeline.config import _Section, load_model_file
from pipeline.errors import UserError

ROBOTS = ("ant",)


class SACPhase(_Section):
    """One entry of `sac.phases`: how experience is collected from `from_step` on.

    OGBench collects its ant-maze data with Gaussian action noise 0.2 on the expert, which its SAC
    never saw in training; our expert trained without noise ends ~14 % of noisy antmaze-medium
    episodes upside down. A later phase trains on with that noise and ends an episode when the ant
    flips, so that the critic learns a flip loses every later reward.
    """

    from_step: int = Field(0, ge=0, description="First environment step of the phase.")
    action_noise: float = Field(
        0.0,
        ge=0,
        description="Std of Gaussian noise added to SAC's action in the environment, clipped to "
        "the action bounds (OGBench's data noise for the ant: 0.2).",
    )
    terminate_upside_down: bool = Field(
        False,
        description="End the episode when the torso's z axis points below the horizon (a "
        "flipped ant cannot right itself); the unhealthy-height end applies always.",
    )


class SACParams(_Section):
    """`sac`: soft actor-critic on the direction task (OGBench's ant expert recipe).

    OGBench trains its ant expert with SAC on `online-ant-v0` in `GymXYWrapper` for 400k steps
    (`data_gen_scripts/commands.sh`, `impls/agents/sac.py`); the defaults are its values.
    """

    total_steps: int = Field(
        500_000,
        ge=1,
        description="Environment steps in total (OGBench's 400k, then 100k of the noisy phase).",
    )
    learning_starts: int = Field(
        10_000, ge=0, description="Steps of uniformly random actions before updates (OGBench)."
    )
    buffer_size: int = Field(
        400_000,
        ge=1,
        description="Replay capacity in transitions; >= total_steps keeps every transition, "
        "as OGBench's 1M buffer does for its 400k steps.",
    )
    batch_size: int = Field(256, ge=1, description="Transitions per gradient step (OGBench).")
    learning_rate: float = Field(1e-4, gt=0, description="Adam lr of actor, critics, alpha.")
    gamma: float = Field(0.99, gt=0, le=1, description="Discount (OGBench).")
    tau: float = Field(0.005, gt=0, le=1, description="Polyak rate of the target critics.")
    hidden: list[int] = Field(
        default_factory=lambda: [256, 256],
        min_length=1,
        description="Hidden widths of the actor and of each critic (OGBench: 256 x 256).",
    )
    activation: Literal["gelu", "relu"] = Field(
        "gelu", description="Hidden activation (OGBench's MLPs: gelu; SB3's default: relu)."
    )
    target_entropy_per_dim: float = Field(
        0.5, ge=0, description="Target entropy = -this * action_dim (OGBench: -0.5 |A|)."
    )
    train_freq: int = Field(1, ge=1, description="Environment steps between updates.")
    gradient_steps: int = Field(1, ge=1, description="Gradient steps per update.")
    resample_interval: int = Field(
        100, ge=1, description="Steps between new random command directions (GymXYWrapper)."
    )
    max_episode_steps: int = Field(1000, ge=1, description="Episode length (online-ant-v0).")
    phases: list[SACPhase] = Field(
        default_factory=lambda: [
            SACPhase(),
            SACPhase(from_step=400_000, action_noise=0.2, terminate_upside_down=True),
        ],
        min_length=1,
        description="How experience is collected, by step (first from_step 0, increasing). A "
        "resumed run may add phases that start at or after its checkpoint, not change past ones.",
    )
    checkpoint_every: int = Field(
        10_000, ge=1, description="Steps between resume checkpoints (and actor exports)."
    )
    log_every: int = Field(1000, ge=1, description="Steps between progress log lines.")
    seed: int = Field(0, description="Seed of the networks, the exploration and the directions.")
    threads: int = Field(1, ge=1, description="Torch CPU threads (1: fastest on shared cores).")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "cpu", description="Torch device; small networks train fastest on CPU."
    )

    @field_validator("phases")
    @classmethod
    def _phases_in_order(cls, phases: list[SACPhase]) -> list[SACPhase]:
        starts = [p.from_step for p in phases]
        if starts[0] != 0 or any(b <= a for a, b in zip(starts, starts[1:], strict=False)):
            raise ValueError(f"from_step must start at 0 and increase, got {starts}")
        return phases

    def phase_at(self, step: int) -> SACPhase:
        """The phase that collects environment step `step`."""
        return [p for p in self.phases if p.from_step <= step][-1]


class ExpertCheckParams(_Section):
    """`check`: the trained actor's quality, deterministic (tanh of the mean), no action noise."""

    speed_episodes: int = Field(
        10, ge=1, description="Direction-task episodes (random directions) for the speed."
    )
    mazes: list[Literal["antmaze-medium-v0", "antmaze-large-v0", "antmaze-giant-v0"]] = Field(
        default_factory=lambda: ["antmaze-medium-v0", "antmaze-large-v0"],
        description="OGBench mazes whose five evaluation tasks the waypoint navigator runs.",
    )
    noisy_episodes: int = Field(
        20,
        ge=0,
        description="Direction-task episodes with `action_noise` added, counting flips (the ant "
        "upside down) as OGBench's noisy data collection would meet them.",
    )
    action_noise: float = Field(0.2, ge=0, description="OGBench's data noise for the ant.")
    episodes_per_task: int = Field(
        10, ge=1, description="Episodes per OGBench task (OGBench reports 50)."
    )
    max_episode_steps: int = Field(1000, ge=1, description="Step limit per maze episode (OGBench).")
    seed: int = Field(0, description="Seed of directions, start noise and goal noise.")


class AntExpertParams(_Section):
    """All of `experts/ant/params.yaml`."""

    sac: SACParams = Field(default_factory=SACParams)
    check: ExpertCheckParams = Field(default_factory=ExpertCheckParams)


def default_params_path(robot: str) -> Path:
    """`experts/<robot>/params.yaml`, relative to the project root."""
    return Path("experts") / robot / "params.yaml"


def check_robot(robot: str) -> str:
    if robot not in ROBOTS:
        raise UserError(f"unknown robot '{robot}'; supported: {', '.join(ROBOTS)}")
    return robot


def load_expert_params(path: str | Path, overrides: list[str] | None = None) -> AntExpertParams:
    """Load and validate an expert params file (or an overlay of one: `extends`), applying
    `section.key=value` overrides.

    Raises:
        UserError: the file is missing or not YAML, its `extends` is broken, a key is unknown or
            a value is bad.
    """
    return load_model_file(
        AntExpertParams,
        path,
        overrides,
        what="expert params file",
        hint="run from the project root",
        sections="sac:, check:",
    )
