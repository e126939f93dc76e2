"""OGBench data: generated with OGBench's own recipe, or imported from its `.npz` files.

- `recipe.py`: OGBench's dataset types, noise and cell pools (`make_recipe`, `Recipe`).
- `generate.py`: `generate_ogbench`, the recipe's loop for the point and the ant.
- `expert.py`: who acts: the point's oracle direction, or the ant expert walking it.
- `npz.py`: `read_ogbench` (OGBench's files, with their `-val.npz`), `write_ogbench_npz`.
- `manipulation.py`, `manip_npz.py`: the manipulation envs' data, generated or imported from
  OGBench's `.npz` (states restored from its qpos / qvel), and their checks.
- `checks.py`: `check_ogbench_dataset`, run by the ingest stage on what it wrote.
- `info.py`: the maze spec, names, units and metadata both paths share.
"""

from pipeline.sources.ogbench.checks import check_ogbench_dataset
from pipeline.sources.ogbench.generate import generate_ogbench
from pipeline.sources.ogbench.npz import maze_of_file, read_ogbench, write_ogbench_npz
from pipeline.sources.ogbench.recipe import (
    DATASET_TYPES,
    NOISE,
    Recipe,
    cells_at_distance,
    make_recipe,
    maze_cells,
)

__all__ = [
    "DATASET_TYPES",
    "NOISE",
    "Recipe",
    "cells_at_distance",
    "check_ogbench_dataset",
    "generate_ogbench",
    "make_recipe",
    "maze_cells",
    "maze_of_file",
    "read_ogbench",
    "write_ogbench_npz",
]
