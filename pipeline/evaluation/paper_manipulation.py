"""Published manipulation numbers our reports put beside ours (results/manipulation.md): OGBench's
table for its state-based manipulation datasets and the OPOSM paper's FrankaKitchen rows
(docs/references.md has the sources). The locomotion numbers are in `pipeline.evaluation.paper`;
these are kept in their own module so that the pipelines depending on that one (the ant mazes'
committed lock) stay valid; they join it when those pipelines next rerun.

Success rates are fractions, (mean, std) as printed. OGBench's are over `paper.OGBENCH_SEEDS`
seeds per method and dataset, success pooled over each dataset's five evaluation tasks.
"""

from __future__ import annotations

from pipeline.evaluation.paper import OGBENCH_METHODS

# OGBench (Park et al., ICLR 2025), its results table for the state-based manipulation datasets
# (play datasets, 1000 episodes x 1001 steps made by its plan oracles), in percent as printed.
_PRINTED = {
    "cube-single-play": ((6, 2), (53, 4), (68, 6), (5, 1), (19, 2), (15, 3)),
    "cube-double-play": ((1, 1), (36, 3), (40, 5), (1, 0), (10, 2), (6, 2)),
    "scene-play": ((5, 1), (42, 4), (51, 4), (5, 1), (19, 2), (38, 3)),
    "puzzle-3x3-play": ((2, 0), (6, 1), (95, 1), (1, 0), (3, 1), (12, 2)),
    "puzzle-4x4-play": ((0, 0), (13, 2), (26, 3), (0, 0), (0, 0), (7, 2)),
}
OGBENCH_MANIPULATION = {
    dataset: {m: (a / 100, b / 100) for m, (a, b) in zip(OGBENCH_METHODS, row, strict=True)}
    for dataset, row in _PRINTED.items()
}

# The OPOSM paper's table 4, FrankaKitchen (D4RL's kitchen-partial and kitchen-mixed, human
# teleoperation data; a different benchmark from OGBench's): success (mean, ± as printed).
KITCHEN_TABLE4 = {
    "kitchen-partial": {"oposm": (0.5625, 0.049), "llp": (0.4307, 0.045)},
    "kitchen-mixed": {"oposm": (0.53125, 0.040), "llp": (0.355, 0.04475)},
}
