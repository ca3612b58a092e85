"""Each counting arm against its constant control, and why it ends where it does:
whether it beats the control (`control_verdicts`), how many of its keys were seen once
(count-1 %), the bonus it actually paid, and whether its curve can be told from its
control's (`why_rows`), each per seed beside the mean; and each claim per seed.

A count bonus that every sampled key gets at n = 1 is a constant shift of the reward:
the control's method. The bonus paid (its mean and spread) and the count-1 % say whether
counting ever made the bonus differ from beta; the control comparison says whether that
showed in learning. While runs are short the comparison says "not run to that length".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from cli.reproduce.analysis import (
    PLATEAU_SHARE,
    TOO_SHORT,
    Analysis,
    ArmCurve,
    Columns,
    count1,
    ended_short,
    same_runs,
)
from cli.reproduce.experiments import arm_configs, control_of, counts


def _score(a: Analysis, arm: ArmCurve) -> tuple[float, float]:
    """Smaller is better: (episodes to convergence or inf, -final success); for
    collisions the final count."""
    if a.fig.metric == "collisions_cum":
        return (arm.final, 0.0)
    if a.fig.kind == "table":
        return (-arm.final, 0.0)
    conv = arm.converged
    return (float(conv) if conv is not None else math.inf, -arm.final)


def summary(a: Analysis, arm: ArmCurve) -> str:
    if not len(arm.episodes):
        return "no points"
    if a.fig.metric == "collisions_cum":
        return f"{arm.final:,.0f} collisions"
    conv = arm.converged
    head = f"converged at {conv:,}" if conv is not None and a.fig.kind != "table" else ""
    tail = f"final {arm.final:.0%}"
    return f"{head}, {tail}" if head else tail


SAME_RUNS = "counting gave every reward the constant's bonus"


def control_verdicts(a: Analysis) -> list[tuple[str, str | None, str, str, str]]:
    """(MACB arm, its control, MACB measured, control measured, verdict) per MACB arm:
    does counting beat the constant bonus of the same beta (the control's point)?"""
    configs = arm_configs(a.fig)
    out: list[tuple[str, str | None, str, str, str]] = []
    for arm_def in a.fig.arms:
        if not counts(configs[arm_def.name]):
            continue
        control = control_of(a.fig, arm_def.name)
        mine = a.arm(arm_def.name)
        if control is None:
            out.append((arm_def.name, None, summary(a, mine), "-", "no control at its beta"))
            continue
        theirs = a.arm(control)
        if not len(mine.episodes) or not len(theirs.episodes):
            out.append((arm_def.name, control, summary(a, mine), summary(a, theirs), "no points"))
            continue
        length = min(mine.length, theirs.length)
        if same_runs(mine, theirs):  # a fact as far as both went, at any length
            verdict = f"the same runs as the control, point for point: {SAME_RUNS}"
            if length < a.fig.episodes:
                verdict += f" (at {length:,} of {a.fig.episodes:,} episodes)"
        else:
            verdict = "beats the control"
            if _score(a, mine) >= _score(a, theirs):
                verdict = "does not beat the control"
            finished = ended_short([mine, theirs], a.fig.episodes)
            if length < a.fig.episodes and finished:
                verdict += f" ({finished})"
            elif length < a.fig.episodes:  # a verdict about the figure's length: not yet
                verdict = (
                    f"{TOO_SHORT} ({length:,} of {a.fig.episodes:,} episodes); so far {verdict}"
                )
        out.append((arm_def.name, control, summary(a, mine), summary(a, theirs), verdict))
    return out


DISTINGUISHED = 0.5  # share of the last points with the spreads apart
SPREAD_VS_BAND = {"std": "the band drawn", "ci75": "wider than the 75% interval drawn"}


@dataclass(frozen=True)
class Paid:
    """The bonus a run paid over its sampled rows: their mean and standard deviation."""

    mean: float
    spread: float

    def __str__(self) -> str:
        return f"{self.mean:.3f} ± {self.spread:.3f}"


def bonus_paid(cols: list[Columns]) -> Paid | None:
    """Over every point of these runs where a bonus was paid (updates had begun): the
    mean of the sampled rows' bonus, and its spread over all of them (each point's
    rows pooled: every point samples as many rows). None: no bonus paid yet."""
    means, stds = [], []
    for c in cols:
        m, s = c.get("bonus_mean", np.zeros(0)), c.get("bonus_std", np.zeros(0))
        ok = ~np.isnan(m) & ~np.isnan(s) & ((m > 0) | (s > 0))
        means.append(m[ok])
        stds.append(s[ok])
    m, s = np.concatenate(means or [np.zeros(0)]), np.concatenate(stds or [np.zeros(0)])
    if not len(m):
        return None
    mean = float(m.mean())
    spread = math.sqrt(max(0.0, float((s**2 + m**2).mean()) - mean**2))
    return Paid(mean, spread)


def _pct(v: float | None) -> str:
    return "-" if v is None or math.isnan(v) else f"{v:.0%}"


def _value(metric: str, v: float | None) -> str:
    if v is None or math.isnan(v):
        return "-"
    return f"{v:,.0f}" if metric == "collisions_cum" else f"{v:.0%}"


def per_seed(a: Analysis, values: dict[int, str]) -> str:
    return ", ".join(f"s{s} {values[s]}" for s in a.seeds if s in values)


def against_control(a: Analysis, mine: ArmCurve, theirs: ArmCurve) -> str:
    """Can the arm's curve be told from its control's: the same runs (`same_runs`),
    else whether their spreads (mean +- one std over seeds) stay apart over the last
    PLATEAU_SHARE of the episodes both reached, which before the figure's length is
    'not run to that length'. The spread, not a confidence band: with 3 seeds a band of
    the mean is narrow enough to part two runs of the same method by chance."""
    if not len(mine.episodes) or not len(theirs.episodes):
        return "no points"
    length = min(mine.length, theirs.length)
    if same_runs(mine, theirs):  # a fact as far as both went, at any length
        text = "the same runs as the control, point for point"
        if length < a.fig.episodes:
            text += f" (as far as both went: {length:,} of {a.fig.episodes:,} episodes)"
        return text
    common = np.intersect1d(mine.episodes, theirs.episodes)
    (lo_m, hi_m), (lo_t, hi_t) = _spread(mine), _spread(theirs)
    im, it = np.isin(mine.episodes, common), np.isin(theirs.episodes, common)
    above = lo_m[im] > hi_t[it]
    below = hi_m[im] < lo_t[it]
    tail = slice(-max(1, round(PLATEAU_SHARE * len(common))), None)
    up, down = float(above[tail].mean()), float(below[tail].mean())
    if up >= DISTINGUISHED:
        text = "distinguishable: above the control"
    elif down >= DISTINGUISHED:
        text = "distinguishable: below the control"
    else:
        text = "not distinguishable: the spreads overlap"
    text += (
        f" (spreads apart at {up + down:.0%} of the last {PLATEAU_SHARE:.0%} of the "
        f"episodes both ran; above at {above.mean():.0%}, below at {below.mean():.0%} "
        "of all of them)"
    )
    if length < a.fig.episodes and (finished := ended_short([mine, theirs], a.fig.episodes)):
        return f"{text} ({finished})"
    if length < a.fig.episodes:
        return f"{TOO_SHORT} ({length:,} of {a.fig.episodes:,} episodes); so far: {text}"
    return text


def _spread(arm: ArmCurve) -> tuple[np.ndarray, np.ndarray]:
    m, s = arm.mean[arm.metric], arm.std[arm.metric]
    return m - s, m + s


def why_rows(a: Analysis) -> list[list[str]]:
    """A row per counting arm: its end, count-1 %, bonus paid, control and verdict."""
    configs = arm_configs(a.fig)
    metric = a.fig.metric
    rows = []
    for arm_def in a.fig.arms:
        name = arm_def.name
        if not counts(configs[name]):
            continue
        mine = a.arm(name)
        seeds = {s: a.for_seed(s) for s in a.seeds if s in mine.seeds}
        end = _value(metric, mine.final if len(mine.episodes) else None)
        end_s = {s: _value(metric, x.arm(name).final) for s, x in seeds.items()}
        c1 = count1(a, name, configs[name])
        c1_s = {s: _pct(_c1(x, name, configs[name])) for s, x in seeds.items()}
        runs = dict(zip(mine.seeds, mine.runs, strict=True))
        paid = bonus_paid([a.points[r] for r in mine.runs if r in a.points])
        paid_s = {s: str(bonus_paid([a.points.get(runs[s], {})]) or "-") for s in seeds}
        constant = paid is not None and paid.spread <= 1e-6 * max(paid.mean, 1e-9)
        control = control_of(a.fig, name)
        verdict = "no control at its beta"
        if control is not None:
            verdict = against_control(a, mine, a.arm(control))
        rows.append(
            [
                name,
                f"{end} ({per_seed(a, end_s)})" if end_s else end,
                (f"{c1:.0f}%" if c1 is not None else "-")
                + (f" ({per_seed(a, c1_s)})" if c1_s else ""),
                (str(paid) if paid else "none paid yet")
                + (" (a constant shift: every sampled key new)" if constant else "")
                + (f" ({per_seed(a, paid_s)})" if paid_s else ""),
                control or "-",
                f"**{verdict}**",
            ]
        )
    return rows


def _c1(a: Analysis, name: str, config: dict[str, Any]) -> float | None:
    v = count1(a, name, config)
    return None if v is None else v / 100


def why_section(a: Analysis) -> list[str]:
    """The page's section: the table and how to read it ([] when no arm counts)."""
    rows = why_rows(a)
    if not rows:
        return []
    band = SPREAD_VS_BAND[a.fig.band]
    lines = [
        "",
        "## Why: what each counting arm counted and paid",
        "",
        "Beside each counting arm's curve: its value at the end (the last episode every seed "
        f"reached), its count-1 % there (the share of its table's keys seen once), the bonus "
        "it paid (the mean ± standard deviation of the bonus on every row it sampled once "
        "updates began; a spread of 0 is a constant shift, the control's method), each for "
        "every seed (s0, s1, ...) after the mean, and whether its curve can be told from its "
        "constant control's: the same runs point for point, or else their spreads (mean ± "
        f"one standard deviation over seeds, {band}) apart over at least "
        f"{DISTINGUISHED:.0%} of the last {PLATEAU_SHARE:.0%} of the episodes both ran.",
        "",
        "| counting arm | at the end | count-1 % | bonus paid | its control "
        "| against the control |",
        "|---|---|---|---|---|---|",
    ]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines


def claim_per_seed(a: Analysis, check: Any) -> str:
    """A claim measured on each seed's runs alone (an arm's name dropped when the claim
    is about one arm)."""
    arms = check.arms()
    parts = []
    for s in a.seeds:
        one = a.for_seed(s)
        if min((one.arm(n).length for n in arms), default=0) == 0:
            parts.append(f"s{s}: no points")
            continue
        text, _ = check.measure(one)
        if len(arms) == 1:
            text = text.removeprefix(f"{arms[0]}: ")
        parts.append(f"s{s}: {text}")
    return "; ".join(parts) or "-"
