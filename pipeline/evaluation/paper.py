"""Published numbers our reports put beside ours, each in one place (docs/references.md has the
sources): the OPOSM paper's (`oposm results`, results/antmaze.md) and OGBench's tables
(results/ogbench-point.md, results/antmaze.md).

Success rates are fractions; `None` where the paper reports nothing. Table 4 (random goals) gives
mean ± the spread it printed; figure 5 is read off the paper code's logged values (antmaze-large,
geom density x0.2 ... x5 of the default); planning time is §4.2's maze2d number per plan. OGBench's
rates are mean ± std over `OGBENCH_SEEDS` seeds, as its table prints them (in %, here / 100).
"""

from __future__ import annotations

# Table 4: success on random goals (mean, ± as printed). Maze2d rows by maze; the antmaze rows by
# D4RL dataset (the paper's own goals, not OGBench's protocol).
TABLE4 = {
    "medium": {"oposm": (1.0, 0.0), "llp": (0.9567, 0.0255)},
    "large": {"oposm": (0.994, 0.011), "llp": (0.8667, 0.0497)},
    "antmaze-medium-diverse": {"oposm": (0.726, 0.047)},
    "antmaze-large-diverse": {"oposm": (0.6507, 0.0496)},
}

# Table 1: success on the fixed goal of D4RL's antmaze (mean, ± as printed).
TABLE1 = {
    "antmaze-medium-diverse": {"oposm": (0.7829, 0.0432)},
    "antmaze-large-diverse": {"oposm": (0.702, 0.046)},
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

# OGBench (Park et al., ICLR 2025), state-based locomotion: success over each dataset's five
# evaluation tasks, (mean, std) over OGBENCH_SEEDS seeds per method. Navigate rows as quoted in
# docs/references.md; stitch rows: OGBench's table as later papers copy it (their navigate rows
# match it cell for cell). No teleport rows are quoted.
OGBENCH_METHODS = ("GCBC", "GCIVL", "GCIQL", "QRL", "CRL", "HIQL")
OGBENCH_SEEDS = 8


def _row(*cells: tuple[int, int]) -> dict[str, tuple[float, float]]:
    """A row as printed (percent) -> method -> (mean, std) as fractions."""
    pairs = zip(OGBENCH_METHODS, cells, strict=True)
    return {method: (mean / 100, std / 100) for method, (mean, std) in pairs}


OGBENCH = {
    "pointmaze-medium-navigate": _row((9, 6), (63, 6), (53, 8), (82, 5), (29, 7), (79, 5)),
    "pointmaze-large-navigate": _row((29, 6), (45, 5), (34, 3), (86, 9), (39, 7), (58, 5)),
    "pointmaze-giant-navigate": _row((1, 2), (0, 0), (0, 0), (68, 7), (27, 10), (46, 9)),
    "pointmaze-medium-stitch": _row((23, 18), (70, 14), (21, 9), (80, 12), (0, 1), (74, 6)),
    "pointmaze-large-stitch": _row((7, 5), (12, 6), (31, 2), (84, 15), (0, 0), (13, 6)),
    "pointmaze-giant-stitch": _row((0, 0), (0, 0), (0, 0), (50, 8), (0, 0), (0, 0)),
    "antmaze-medium-navigate": _row((29, 4), (72, 8), (71, 4), (88, 3), (95, 1), (96, 1)),
    "antmaze-large-navigate": _row((24, 2), (16, 5), (34, 4), (75, 6), (83, 4), (91, 2)),
}
