"""Importers from other formats into our `DatasetInfo` + `Episode` stream, and LeRobot export.

- `read_lerobot`: a LeRobot v3.0 dataset, through `lerobot`.
- `read_d4rl`: a D4RL hdf5 file, through h5py (maze2d coordinates converted for PointMaze).
- `read_minari`: a local Minari dataset, through `minari`.
- `read_ogbench` / `generate_ogbench`: OGBench maze data, from its `.npz` files or its recipe;
  `open_manipulation`: OGBench's manipulation data (cube, scene), from its recipe or OGBench's
  `.npz` files (states restored from their qpos / qvel).
- `export_lerobot`: one of our MCAP datasets as a LeRobot v3.0 dataset.

`open_source(params.ingest)` picks the importer named by `ingest.source`. `lerobot` and `minari`
are imported inside the functions that use them (lerobot takes seconds to import).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.envs.manipspace.env import is_manipspace
from pipeline.errors import UserError
from pipeline.sources.common import ImportedDataset, is_simulated_maze
from pipeline.sources.d4rl import read_d4rl, write_d4rl
from pipeline.sources.lerobot_export import ExportSummary, export_lerobot
from pipeline.sources.lerobot_import import read_lerobot
from pipeline.sources.minari_import import read_minari

if TYPE_CHECKING:
    from pipeline.config import IngestParams

__all__ = [
    "ExportSummary",
    "ImportedDataset",
    "export_lerobot",
    "is_simulated_maze",
    "open_source",
    "read_d4rl",
    "read_lerobot",
    "read_minari",
    "write_d4rl",
]


def open_source(
    cfg: IngestParams, progress: bool = False, cache_root: Path | None = None
) -> ImportedDataset:
    """Open the source named by `cfg.source` ("lerobot", "d4rl", "minari" or "ogbench") with its
    section; data generated with OGBench's recipes are kept under `cache_root` as they are made
    (a killed run resumes from them)."""
    if cfg.source == "lerobot":
        lr = cfg.lerobot
        return read_lerobot(
            lr.repo_id,
            cfg.name,
            root=lr.root,
            state_features=lr.state_features,
            action_feature=lr.action_feature,
            progress=progress,
        )
    if cfg.source == "d4rl":
        if not cfg.d4rl.path:
            raise UserError("set ingest.d4rl.path to the D4RL .hdf5 file to import")
        return read_d4rl(
            Path(cfg.d4rl.path),
            cfg.name,
            env_id=cfg.d4rl.env_id,
            control_period=cfg.d4rl.control_period,
            progress=progress,
        )
    if cfg.source == "minari":
        mn = cfg.minari
        return read_minari(
            cfg.name,
            dataset_id=mn.dataset_id,
            path=mn.path,
            state_keys=mn.state_keys,
            action_key=mn.action_key,
            goal_key=mn.goal_key,
            control_period=mn.control_period,
            progress=progress,
        )
    if cfg.source == "ogbench":
        return open_ogbench(cfg, progress, cache_root)
    raise UserError(
        f"ingest.source {cfg.source!r} is not an import; use lerobot, d4rl, minari or ogbench"
    )


def open_ogbench(
    cfg: IngestParams, progress: bool = False, cache_root: Path | None = None
) -> ImportedDataset:
    """`ingest.ogbench`: import its `path`, or generate with OGBench's recipe (kept under
    `cache_root` as it is made, when given)."""
    from pipeline.sources.ogbench import generate_ogbench, make_recipe, read_ogbench

    og = cfg.ogbench
    if is_manipspace(og.env_id):
        from pipeline.sources.ogbench.manipulation import open_manipulation

        if og.expert:
            raise UserError(
                f"ingest.ogbench.expert is for ant mazes; {og.env_id}'s data come from OGBench's "
                "scripted oracles: set ingest.ogbench.expert to null"
            )
        return open_manipulation(
            og.env_id, og.dataset_type, cfg.episodes, cfg.episode_steps, cfg.seed, cfg.name,
            og.noise, og.path, progress, og.workers, og.include_val, cache_root,
        )  # fmt: skip
    if og.path:
        if og.expert:
            raise UserError(
                "ingest.ogbench.expert generates ant data; importing ingest.ogbench.path does "
                "not use it: set one of them to null"
            )
        return read_ogbench(og.path, cfg.name, og.env_id, og.include_val, progress)
    recipe = make_recipe(
        og.env_id, og.dataset_type, cfg.episodes, cfg.episode_steps, cfg.seed, og.noise, og.expert
    )
    return generate_ogbench(recipe, cfg.name, progress, og.workers, cache_root)
