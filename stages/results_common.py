"""Numbers and verdicts shared by the results stage's experiments: reports, rates, cells."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

from pipeline.errors import UserError
from pipeline.evaluation.proportions import difference_interval, wilson_interval

Report = dict[str, Any]


def read(path: Path) -> Report | None:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: not valid JSON ({exc.msg}); re-run its stage") from exc


def pct(x: float) -> str:
    return f"{100 * x:.1f}"


def rate(wins: int, n: int) -> dict[str, Any]:
    lo, hi = wilson_interval(wins, n)
    return {"successes": wins, "episodes": n, "rate": wins / n, "ci95": [lo, hi]}


def cell(r: dict[str, Any] | None) -> str:
    if r is None:
        return "–"
    lo, hi = r["ci95"]
    return f"{pct(r['rate'])} [{pct(lo)}, {pct(hi)}]"


def versus(a: dict[str, Any], b: dict[str, Any]) -> tuple[str, list[float]]:
    """Verdict on `a > b` (success dicts of `_rate`) and the interval of the difference."""
    lo, hi = difference_interval(a["successes"], a["episodes"], b["successes"], b["episodes"])
    verdict = "holds" if lo > 0 else "does not hold" if hi < 0 else "inconclusive"
    return verdict, [lo, hi]


def separated(a: list[float], b: list[float]) -> str:
    """Verdict on "a > b" from per-seed values: every a above every b holds (for 3 seeds each an
    exact permutation test at p = 1/20), every a below every b does not hold, else inconclusive."""
    if min(a) > max(b):
        return "holds"
    return "does not hold" if max(a) < min(b) else "inconclusive"


_CODE = ("*.py", "pyproject.toml", "uv.lock")  # what DVC runs do not rewrite (locks, metrics)


def code_version(repo: Path) -> str | None:
    """The git commit the results were assembled at (`+dirty` with uncommitted code changes)."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True, text=True
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", *_CODE],
            cwd=repo,
            capture_output=True,
            text=True,
        )
    except OSError:
        return None
    if head.returncode != 0:
        return None
    return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
