"""Published ant-maze numbers that `pipeline.evaluation.paper` does not hold: the paper's LLP rows
(low-level planning with a single-step model, its §4.2 baseline: its table 1, D4RL's fixed antmaze
goal, and table 4, random goals; mean and the ± it printed, as fractions), which
`pipeline.reporting.antmaze` puts beside our LLP on the same tasks as OPOSM; its table 3 (EM
against naive VI) on the ant; and OGBench's antmaze-giant-navigate row. Kept out of
`pipeline.evaluation.paper` so that the pipelines depending on that module (the paper's
experiments, the manipulation datasets') keep valid locks.
"""

from __future__ import annotations

from pipeline.evaluation.paper import OGBENCH_METHODS

# Table 1: "Success Rates for Antmaze Environments", column LLP.
TABLE1_LLP = {
    "antmaze-medium-diverse": (0.312, 0.0574),
    "antmaze-large-diverse": (0.144, 0.0435),
}

# Table 4: random goals, column LLP.
TABLE4_LLP = {
    "antmaze-medium-diverse": (0.328, 0.0582),
    "antmaze-large-diverse": (0.30, 0.0568),
}

# Table 3: EM against naive VI (success, mean ± as printed), the antmaze rows.
TABLE3 = {
    "antmaze-medium-diverse": {"em": (0.7829, 0.0432), "vi": (0.744, 0.044)},
    "antmaze-large-diverse": {"em": (0.702, 0.046), "vi": (0.583, 0.056)},
}

# OGBench's paper (Park et al., ICLR 2025), its table of state-based locomotion results, the
# antmaze-giant-navigate row: mean ± std over 8 seeds in percent, as printed, in the order of
# `paper.OGBENCH_METHODS` (its medium and large rows are in `paper.OGBENCH`; docs/references.md).
_OGBENCH_GIANT = ((0, 0), (0, 0), (0, 0), (14, 3), (16, 3), (65, 5))
OGBENCH = {
    "antmaze-giant-navigate": {
        method: (mean / 100, std / 100)
        for method, (mean, std) in zip(OGBENCH_METHODS, _OGBENCH_GIANT, strict=True)
    },
}
