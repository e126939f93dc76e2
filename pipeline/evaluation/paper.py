"""The paper's numbers that `oposm results` puts beside ours (docs/references.md has sources).

Success rates are fractions; `None` where the paper reports nothing. Table 4 (random goals) gives
mean ± the spread it printed; figure 5 is read off the paper code's logged values (antmaze-large,
geom density x0.2 ... x5 of the default); planning time is §4.2's maze2d number per plan.
"""

from __future__ import annotations

# Table 4, maze2d rows: success on random goals (mean, ± as printed).
TABLE4 = {
    "medium": {"oposm": (1.0, 0.0), "llp": (0.9567, 0.0255)},
    "large": {"oposm": (0.994, 0.011), "llp": (0.8667, 0.0497)},
}

# Episodes behind each maze2d success rate: "until intervals were under 10 %, 250-300 for mazes"
# (the lower end, so the paper's rate is given its widest interval).
EPISODES_MAZE2D = 250

# Figure 5 (antmaze-large, fixed goal): success per density factor.
FIGURE5_FACTORS = (0.2, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0)
FIGURE5 = {
    "oposm": (0.35, 0.51, 0.70, 0.816, 0.73, 0.686, 0.607),
    "expert": (0.20, 0.493, 0.80, 0.80, 0.893, 0.36, 0.0),
    "opal_bc": (0.233, 0.373, 0.53, 0.587, 0.410, 0.397, 0.263),
}

# §4.2 / table 1: seconds to find a plan in maze2d.
PLAN_SECONDS = {"oposm": 0.051, "llp": 3.02}
