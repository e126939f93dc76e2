"""Intervals for success rates: one proportion (Wilson) and the difference of two (Newcombe).

Written out, although scipy is a dependency: scipy has no interval for a difference of two
proportions, and its Wilson interval (`scipy.stats.binomtest(k, n).proportion_ci(method="wilson")`,
the same values as `wilson_interval`) would cost the results stage the import of `scipy.stats`
(about a second) for six lines of arithmetic. The results stage uses them without loading any of
the deploy machinery.
"""

from __future__ import annotations

import math
from statistics import NormalDist


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion (Wilson, 1927).

    Unlike the normal approximation it stays inside [0, 1] and is sensible at 0 or n successes
    (e.g. 100 / 100 -> [0.963, 1.0]). Written out: see the module docstring.
    """
    if n == 0:
        return 0.0, 1.0
    z = NormalDist().inv_cdf(0.5 + confidence / 2)
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def difference_interval(
    wins_a: int, n_a: int, wins_b: int, n_b: int, confidence: float = 0.95
) -> tuple[float, float]:
    """95 % interval of the difference of two proportions `a - b` (Newcombe, 1998, method 10:
    the hybrid score interval built from each proportion's Wilson interval).

    It keeps the Wilson interval's good behaviour near 0 and 1 (e.g. 200 / 200 vs 190 / 200),
    where the normal approximation is too narrow.
    """
    p_a, p_b = wins_a / n_a, wins_b / n_b
    lo_a, hi_a = wilson_interval(wins_a, n_a, confidence)
    lo_b, hi_b = wilson_interval(wins_b, n_b, confidence)
    d = p_a - p_b
    low = d - math.sqrt((p_a - lo_a) ** 2 + (hi_b - p_b) ** 2)
    high = d + math.sqrt((hi_a - p_a) ** 2 + (p_b - lo_b) ** 2)
    return max(-1.0, low), min(1.0, high)
