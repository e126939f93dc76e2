"""Published numbers of methods that came after OGBench, on OGBench's point mazes and protocol
(its five evaluation tasks, 1000 steps): the reports put them beside OGBench's own table
(`pipeline.evaluation.paper.OGBENCH`; docs/references.md has the sources). Kept in their own
module so that the pipelines depending on `paper` (the ant mazes', the manipulation datasets')
keep valid locks; only the point mazes' report reads this one.

Only numbers read in the paper's own table are here. Read elsewhere, not yet in a paper's table,
and so left out: ALPS (arXiv 2602.05031; giant-stitch 98 ± 1, large-stitch 96 ± 2 as secondary
sources quote it), GCIQL + TTGS (arXiv 2510.07257; giant-stitch 98.0 ± 1.4, idem) and SCoTS
(arXiv 2506.00895; giant-stitch 100, whose code runs up to 2000 steps: not OGBench's protocol).
"""

from __future__ import annotations

# SAW, "Flattening Hierarchies with Policy Bootstrapping" (Zhou and Kao, NeurIPS 2025,
# arXiv 2505.14975): its own runs, mean ± std over 8 seeds, in percent as printed. Navigate:
# its table 1; stitch: its table 3 (appendix J).
_SAW = {
    "pointmaze-medium-navigate": (97, 2),
    "pointmaze-large-navigate": (85, 10),
    "pointmaze-giant-navigate": (68, 8),
    "pointmaze-medium-stitch": (87, 4),
    "pointmaze-large-stitch": (8, 9),
    "pointmaze-giant-stitch": (0, 0),
}

# method -> seeds behind each mean ± std
SEEDS = {"SAW": 8}

# OGBench dataset -> method -> (mean, std) as fractions
AFTER_OGBENCH = {dataset: {"SAW": (mean / 100, std / 100)} for dataset, (mean, std) in _SAW.items()}
