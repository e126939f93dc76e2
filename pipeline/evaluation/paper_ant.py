"""The paper's LLP rows on the ant mazes (low-level planning with a single-step model, its §4.2
baseline): its table 1 (D4RL's fixed antmaze goal) and table 4 (random goals), mean and the ±
it printed, as fractions. `pipeline.reporting.antmaze` puts them beside our LLP on the same tasks
as OPOSM. Kept out of `pipeline.evaluation.paper` so that the pipelines depending on that module
(the paper's experiments, the manipulation datasets') keep valid locks.
"""

from __future__ import annotations

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
