"""What every report in `results/` shares: reading run reports, the one format of a rate and its
interval, one verdict rule per kind of claim, and the stamp saying where a report came from.

Format. A success rate is written in % with its 95 % Wilson interval in brackets,
`percent(0.965, 0.93, 0.983)` -> "96.5 [93.0, 98.3]" (`digits=0` for wide tables: "96 [93, 98]");
an interval of a difference in percentage points, `points(lo, hi)` -> "[1.2, 8.0]"; a published
mean and std, `mean_std(0.82, 0.05)` -> "82 ± 5".

Verdicts (`HOLDS`, `FAILS`, `INCONCLUSIVE`), each kind of claim with its one rule:

1. Two of our success rates, "a is above b" (`versus`): the Newcombe (1998, method 10) 95 %
   interval of a - b; holds when it lies above 0, does not hold when below 0, else inconclusive.
2. Ours against a published rate over a known number of episodes, "ours reproduces it"
   (`reproduces`): the same interval of ours - theirs (their rate taken as that many episodes);
   holds unless it lies below 0 (reaching more than the paper is no failure to reproduce).
3. Ours against a published mean ± std over seeds, "ours is above it" (`above_published`): the
   MOVER interval of ours - theirs (Zou and Donner, 2008: Newcombe's construction, from our
   Wilson interval and the t interval of their mean over the seeds); three-way as in 1. "Ours is
   above every published method" (`above_every`) holds when it holds against each, does not
   hold when it fails against one, else inconclusive.
4. Per-seed values, "a is above b" (`separated`): every a above every b holds (for 3 seeds each
   an exact permutation test at p = 1/20), every a below every b does not hold, else
   inconclusive.
5. Robustness to changed dynamics (paper figure 5), "a keeps more of its success than b": rule 1
   on each agent's success pooled over the perturbed settings (`off_nominal`). The share of its
   nominal success an agent keeps (`kept_share`) is descriptive: no verdict rests on it (a ratio
   of two rates has no interval here, and the nominal rate it divides by is itself noisy).

Stamp (`stamp`, `stamp_text`): the code's commit (`code_version`), the machine (`machine`), and,
for a report written by a DVC stage, the stage and a digest of the other stages' entries in its
dvc.lock (`dvc_stamp`, `lock_digest`): the exact inputs the report was made from.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import platform
import subprocess
from collections.abc import Mapping
from importlib import metadata
from pathlib import Path
from typing import Any

import yaml

from pipeline.errors import UserError
from pipeline.evaluation.proportions import difference_interval, wilson_interval
from pipeline.io import atomic_path, write_json

Report = dict[str, Any]

HOLDS, FAILS, INCONCLUSIVE = "holds", "does not hold", "inconclusive"


def _load(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: not valid JSON ({exc.msg}); re-run its stage") from exc


def with_timings(report: Any, timings: Any) -> Any:
    """`report` with the wall-clock measurements its stage wrote apart (`data/timings/`, the
    nesting of the report: `stages.report.split_timings`) put back in place."""
    if not isinstance(report, dict) or not isinstance(timings, dict):
        return report
    merged = dict(report)
    for key, value in timings.items():
        merged[key] = with_timings(merged[key], value) if key in merged else value
    return merged


def read(path: Path) -> Report | None:
    """A JSON report, or None when it does not exist. A stage report
    (`<data>/reports/<stage>/report.json` or dvclive's `metrics.json`) comes with its stage's
    wall-clock measurements from `<data>/timings/<stage>.json` where that file exists (they are
    measurements of the machine that ran it, kept out of the stage's outputs).

    Raises:
        UserError: the file is not valid JSON (one line naming it).
    """
    report = _load(path)
    if report is None or path.parent.parent.name != "reports":
        return report
    if path.name not in ("report.json", "metrics.json"):
        return report
    timings = _load(path.parents[2] / "timings" / f"{path.parent.name}.json")
    return with_timings(report, timings) if timings is not None else report


# --- format -------------------------------------------------------------------------------------


def train_speed(train: Report) -> str:
    """Steps/s and minutes from a train report's timings, or "time not recorded"."""
    if "steps_per_s" not in train or "wall_s" not in train:
        return "time not recorded"
    return f"{train['steps_per_s']:.2f} steps/s, {train['wall_s'] / 60:.0f} min"


def pct(x: float, digits: int = 1) -> str:
    """A fraction in %: 0.965 -> "96.5" (no "-0" for a value that rounds to 0)."""
    text = f"{100 * x:.{digits}f}"
    return text.removeprefix("-") if float(text) == 0 else text


def percent(
    rate: float | None, low: float | None = None, high: float | None = None, digits: int = 1
) -> str:
    """A rate and its interval in %: "96.5 [93.0, 98.3]"; the rate alone without an interval;
    "–" for None."""
    if rate is None:
        return "–"
    if low is None or high is None:
        return pct(rate, digits)
    return f"{pct(rate, digits)} [{pct(low, digits)}, {pct(high, digits)}]"


def cell(r: Mapping[str, Any] | None, digits: int = 1) -> str:
    """`percent` of a `rate` dict (or "–")."""
    if r is None:
        return "–"
    return percent(r["rate"], *r["ci95"], digits=digits)


def points(interval: tuple[float, float] | list[float], digits: int = 1) -> str:
    """An interval of a difference of rates, in percentage points: "[1.2, 8.0]"."""
    lo, hi = interval
    return f"[{pct(lo, digits)}, {pct(hi, digits)}]"


def mean_std(mean: float, std: float, digits: int = 0) -> str:
    """A published mean ± std, in %: "82 ± 5"."""
    return f"{pct(mean, digits)} ± {pct(std, digits)}"


# --- rates --------------------------------------------------------------------------------------


def rate(wins: int, n: int) -> dict[str, Any]:
    """Successes of n episodes: the rate and its 95 % Wilson interval."""
    lo, hi = wilson_interval(wins, n)
    return {"successes": wins, "episodes": n, "rate": wins / n, "ci95": [lo, hi]}


def rate_of(row: Mapping[str, Any]) -> dict[str, Any]:
    """A `rate` from a deploy report's task row (`successes`, `episodes`)."""
    return rate(row["successes"], row["episodes"])


def pooled(rates: list[Mapping[str, Any]]) -> dict[str, Any]:
    """One `rate` of the episodes of several."""
    return rate(sum(r["successes"] for r in rates), sum(r["episodes"] for r in rates))


# --- verdicts -----------------------------------------------------------------------------------


def three_way(lo: float, hi: float) -> str:
    """The verdict on "x > 0" from an interval of x."""
    return HOLDS if lo > 0 else FAILS if hi < 0 else INCONCLUSIVE


def versus(a: Mapping[str, Any], b: Mapping[str, Any]) -> tuple[str, list[float]]:
    """Rule 1, "a's success rate is above b's" (`rate` dicts): the verdict and the Newcombe
    interval of a - b."""
    lo, hi = difference_interval(a["successes"], a["episodes"], b["successes"], b["episodes"])
    return three_way(lo, hi), [lo, hi]


def reproduces(ours: Mapping[str, Any], published: float, episodes: int) -> tuple[str, list[float]]:
    """Rule 2, "ours reproduces a published rate over `episodes` episodes": holds unless the
    Newcombe interval of ours - theirs lies below 0."""
    _, (lo, hi) = versus(ours, rate(round(published * episodes), episodes))
    return (FAILS if hi < 0 else HOLDS), [lo, hi]


def mean_interval(mean: float, std: float, seeds: int) -> tuple[float, float]:
    """The 95 % t interval of a mean over `seeds` seeds with sample std `std`."""
    from scipy.stats import t

    half = float(t.ppf(0.975, seeds - 1)) * std / math.sqrt(seeds) if seeds > 1 else math.inf
    return mean - half, mean + half


def above_published(
    ours: Mapping[str, Any], mean: float, std: float, seeds: int
) -> tuple[str, list[float]]:
    """Rule 3, "our rate is above a published mean ± std over `seeds` seeds": the verdict and the
    MOVER interval of ours - theirs."""
    p, (lo_p, hi_p) = ours["rate"], ours["ci95"]
    lo_m, hi_m = mean_interval(mean, std, seeds)
    d = p - mean
    lo = d - math.sqrt((p - lo_p) ** 2 + (hi_m - mean) ** 2)
    hi = d + math.sqrt((hi_p - p) ** 2 + (mean - lo_m) ** 2)
    lo, hi = max(-1.0, lo), min(1.0, hi)
    return three_way(lo, hi), [lo, hi]


def above_every(
    ours: Mapping[str, Any], table: Mapping[str, tuple[float, float]], seeds: int
) -> tuple[str, str, list[float]]:
    """Rule 3 against every method of a published row (method -> (mean, std)): the verdict, the
    method deciding it (of those it fails against, the one furthest above ours; else the one whose
    interval comes closest to 0) and that interval."""
    each = {m: above_published(ours, mean, std, seeds) for m, (mean, std) in table.items()}
    failed = [m for m, (v, _) in each.items() if v == FAILS]
    if failed:
        method = min(failed, key=lambda m: each[m][1][1])
    else:
        method = min(each, key=lambda m: each[m][1][0])
    verdicts = {v for v, _ in each.values()}
    word = FAILS if failed else HOLDS if verdicts == {HOLDS} else INCONCLUSIVE
    return word, method, each[method][1]


def separated(a: list[float], b: list[float]) -> str:
    """Rule 4, "a > b" from per-seed values: every a above every b holds (for 3 seeds each an
    exact permutation test at p = 1/20), every a below every b does not hold, else
    inconclusive."""
    if min(a) > max(b):
        return HOLDS
    return FAILS if max(a) < min(b) else INCONCLUSIVE


def off_nominal(by_factor: Mapping[Any, Mapping[str, Any]], nominal: float = 1.0) -> dict | None:
    """Rule 5's numbers: one agent's `rate`s per factor (keys: the factor, a number or its
    string) pooled over every factor but `nominal`; None when only the nominal ran."""
    off = [r for f, r in by_factor.items() if float(f) != nominal]
    return pooled(off) if off else None


def kept_share(by_factor: Mapping[Any, Mapping[str, Any]], nominal: float = 1.0) -> float | None:
    """The mean success over the perturbed factors as a share of the success at `nominal`
    (descriptive: no verdict rests on it)."""
    base = next((r["rate"] for f, r in by_factor.items() if float(f) == nominal), None)
    others = [r["rate"] for f, r in by_factor.items() if float(f) != nominal]
    return sum(others) / len(others) / base if base and others else None


# --- what ran -----------------------------------------------------------------------------------


def read_all(paths: list[Path], stage: str) -> list[Report]:
    """The reports at `paths`, in order, for a page that needs every one of them.

    Raises:
        UserError: one is missing (naming it and the `stage` that writes it) or not valid JSON.
    """
    reports = []
    for path in paths:
        report = read(path)
        if report is None:
            raise UserError(f"{path} does not exist; run its stage ({stage}) first")
        reports.append(report)
    return reports


def lock_commands(lock: Path, exclude: str = "report") -> list[str]:
    """The command of every stage a dvc.lock recorded (`exclude` left out), as
    `<cmd>   # <stage>`, in the lock's order."""
    try:
        stages = (yaml.safe_load(lock.read_text()) or {}).get("stages", {})
    except FileNotFoundError:
        return []
    return [f"{entry['cmd']}   # {name}" for name, entry in stages.items() if name != exclude]


# --- stamp --------------------------------------------------------------------------------------

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


def _gpus() -> list[str]:
    names = []
    for info in sorted(Path("/proc/driver/nvidia/gpus").glob("*/information")):
        for line in info.read_text(errors="replace").splitlines():
            if line.startswith("Model:"):
                names.append(line.split(":", 1)[1].strip())
    return names


def machine() -> str:
    """This machine in one line: the CPU model (and whether it multiplies bfloat16 natively),
    its cores, any NVIDIA GPUs, torch's version."""
    cpuinfo = Path("/proc/cpuinfo")
    text = cpuinfo.read_text(errors="replace") if cpuinfo.exists() else ""
    models = [line.split(":", 1)[1].strip() for line in text.splitlines()
              if line.startswith("model name")]  # fmt: skip
    cpu = models[0] if models else platform.processor() or platform.machine()
    units = [name for flag, name in ((" avx512_bf16", "AVX512-BF16"), (" amx_bf16", "AMX-BF16"))
             if flag in text]  # fmt: skip
    bf16 = f" (with {', '.join(units)})" if units else ""
    gpus = _gpus()
    gpu = f", GPU {', '.join(gpus)}" if gpus else ""
    try:
        torch = f", torch {metadata.version('torch')}"
    except metadata.PackageNotFoundError:
        torch = ""
    return f"{cpu}{bf16}, {os.cpu_count()} cores{gpu}{torch}"


def lock_digest(lock: Path, exclude: str | None = None) -> str | None:
    """sha256 of a dvc.lock's stage entries (`exclude` left out: the stage reading it), as
    sorted JSON; None without a lock. Recompute it on a checkout to see that a report came from
    that lock."""
    try:
        stages = (yaml.safe_load(lock.read_text()) or {}).get("stages", {})
    except FileNotFoundError:
        return None
    entries = {name: entry for name, entry in stages.items() if name != exclude}
    return hashlib.sha256(json.dumps(entries, sort_keys=True).encode()).hexdigest()


def dvc_stamp(environ: Mapping[str, str] | None = None) -> dict[str, Any] | None:
    """The DVC stage writing this report (DVC sets `DVC_STAGE` and `DVC_ROOT` for its
    commands): its address, its dvc.lock and `lock_digest` of the lock's other stages (DVC
    writes each stage's entry when it finishes, so these are the entries of what the report
    read). None outside DVC."""
    env = os.environ if environ is None else environ
    stage = env.get("DVC_STAGE")
    if not stage:
        return None
    dvcfile, sep, name = stage.rpartition(":")
    if not sep:
        dvcfile, name = "dvc.yaml", stage
    lock = Path(dvcfile).with_suffix(".lock")
    digest = lock_digest(Path(env.get("DVC_ROOT", ".")) / lock, exclude=name)
    return {"stage": stage, "lock": lock.as_posix(), "upstream_sha256": digest}


def stamp(repo: Path, environ: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Where a report comes from: `commit` (`code_version`), `machine`, `dvc` (`dvc_stamp`)."""
    return {"commit": code_version(repo), "machine": machine(), "dvc": dvc_stamp(environ)}


def stamp_text(s: Mapping[str, Any]) -> str:
    """A stamp in words: "assembled on <machine>, code at commit <commit>", and for a DVC stage
    "; written by DVC stage `<stage>` from <lock> entries of sha256 <first 12 digits>"."""
    text = f"assembled on {s.get('machine')}, code at commit {s.get('commit')}"
    dvc = s.get("dvc")
    if dvc:
        digest = (dvc.get("upstream_sha256") or "none")[:12]
        text += (
            f"; written by DVC stage `{dvc['stage']}` from the other entries of {dvc['lock']} "
            f"(sha256 {digest})"
        )
    return text


# --- writing ------------------------------------------------------------------------------------


def write_report(path: Path, report: Mapping[str, Any]) -> None:
    """One report as JSON (its folder made), written atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, report)


def write_page(out: Path, stem: str, results: Mapping[str, Any], text: str) -> None:
    """A results page: `out/<stem>.json` (`results`) and `out/<stem>.md` (`text`), atomically."""
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / f"{stem}.json", results)
    with atomic_path(out / f"{stem}.md") as tmp:
        tmp.write_text(text)
