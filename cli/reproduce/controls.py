"""Each counting arm against its constant control, and why it ends where it does:
whether it beats the control (`control_verdicts`, by the rule that tells its curve
from the control's: `distinguish`), how many of its keys were seen once
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
    does counting beat the constant bonus of the same beta (the control's point)? By
    the Why table's rule (`distinguish`), so the two sections never disagree: beats it
    when its spread is apart from the control's on the better side (above; below for
    collisions), does not beat it on the other side, and is not distinguishable from it
    while the spreads overlap."""
    configs = arm_configs(a.fig)
    out: list[tuple[str, str | None, str, str, str]] = []
    better = "below" if a.fig.metric == "collisions_cum" else "above"
    for arm_def in a.fig.arms:
        if not counts(configs[arm_def.name]):
            continue
        control = control_of(a.fig, arm_def.name)
        mine = a.arm(arm_def.name)
        if control is None:
            out.append((arm_def.name, None, summary(a, mine), "-", "no control at its beta"))
            continue
        theirs = a.arm(control)
        d = distinguish(mine, theirs)
        if d is None:
            out.append((arm_def.name, control, summary(a, mine), summary(a, theirs), "no points"))
            continue
        short = d.length < a.fig.episodes
        finished = ended_short([mine, theirs], a.fig.episodes) if short else None
        if d.side == "same":  # a fact as far as both went, at any length
            verdict = f"the same runs as the control, point for point: {SAME_RUNS}"
            if short:
                verdict += f" (at {d.length:,} of {a.fig.episodes:,} episodes)"
        elif d.side == "overlap":
            verdict = "not distinguishable from the control"
            if finished:  # every run ended by its early-stop rule: a verdict all the same
                verdict += f" ({finished})"
            elif short:
                verdict = f"{TOO_SHORT} ({d.length:,} of {a.fig.episodes:,} episodes); not "
                verdict += "distinguishable so far"
        else:
            verdict = "beats the control" if d.side == better else "does not beat the control"
            if finished:
                verdict += f" ({finished})"
            elif short:  # a verdict about the figure's length: not yet
                verdict = (
                    f"{TOO_SHORT} ({d.length:,} of {a.fig.episodes:,} episodes); so far {verdict}"
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


@dataclass(frozen=True)
class Distinction:
    """An arm's curve against its control's: `side` "same" (the same runs, point for
    point), "above" or "below" (their spreads apart on that side over at least
    DISTINGUISHED of the last PLATEAU_SHARE of the episodes both ran) or "overlap";
    `length` the episodes both ran; the shares of those last points (`up`, `down`) and
    of all common points (`above`, `below`) with the spreads apart; `by` "end" when the
    last points part them, "area" when only the whole run does (one arm learns faster:
    each seed's mean over the episodes both ran, spreads apart)."""

    side: str
    length: int
    up: float = 0.0
    down: float = 0.0
    above: float = 0.0
    below: float = 0.0
    by: str = "end"  # what parted them: "end" (the last points) or "area" (the whole run)


def distinguish(mine: ArmCurve, theirs: ArmCurve) -> Distinction | None:
    """Can the arm's curve be told from its control's (None: one has no points): the
    same runs (`same_runs`), else whether their spreads (mean +- one std over seeds)
    stay apart over the last PLATEAU_SHARE of the episodes both reached. The spread,
    not a confidence band: with 3 seeds a band of the mean is narrow enough to part two
    runs of the same method by chance."""
    if not len(mine.episodes) or not len(theirs.episodes):
        return None
    length = min(mine.length, theirs.length)
    if same_runs(mine, theirs):
        return Distinction("same", length)
    common = np.intersect1d(mine.episodes, theirs.episodes)
    (lo_m, hi_m), (lo_t, hi_t) = _spread(mine), _spread(theirs)
    im, it = np.isin(mine.episodes, common), np.isin(theirs.episodes, common)
    above = lo_m[im] > hi_t[it]
    below = hi_m[im] < lo_t[it]
    tail = slice(-max(1, round(PLATEAU_SHARE * len(common))), None)
    up, down = float(above[tail].mean()), float(below[tail].mean())
    side = "above" if up >= DISTINGUISHED else "below" if down >= DISTINGUISHED else "overlap"
    by = "end"
    if side == "overlap":  # the same end, reached sooner or later: the area says which
        side = _area_side(mine, theirs, common)
        by = "area" if side != "overlap" else "end"
    return Distinction(side, length, up, down, float(above.mean()), float(below.mean()), by)


def _area_side(mine: ArmCurve, theirs: ArmCurve, common: np.ndarray) -> str:
    """'above' / 'below' when each seed's mean of its smoothed curve over the `common`
    episodes (the area under it: how soon and how high it learned) has its spread
    (mean +- one std over seeds) apart from the control's, else 'overlap'."""
    metric = mine.metric
    if metric not in mine.smoothed or metric not in theirs.smoothed or not len(common):
        return "overlap"
    a = mine.smoothed[metric][:, np.isin(mine.episodes, common)].mean(axis=1)
    b = theirs.smoothed[metric][:, np.isin(theirs.episodes, common)].mean(axis=1)
    if a.mean() - a.std() > b.mean() + b.std():
        return "above"
    if a.mean() + a.std() < b.mean() - b.std():
        return "below"
    return "overlap"


def against_control(a: Analysis, mine: ArmCurve, theirs: ArmCurve) -> str:
    """The Why table's words for `distinguish`, which before the figure's length are
    'not run to that length' (the same runs are a fact at any length)."""
    d = distinguish(mine, theirs)
    if d is None:
        return "no points"
    if d.side == "same":
        text = "the same runs as the control, point for point"
        if d.length < a.fig.episodes:
            text += f" (as far as both went: {d.length:,} of {a.fig.episodes:,} episodes)"
        return text
    text = {
        "above": "distinguishable: above the control",
        "below": "distinguishable: below the control",
        "overlap": "not distinguishable: the spreads overlap",
    }[d.side]
    if d.by == "area":
        text += " over the run (each seed's mean over the episodes both ran), not at the end"
    text += (
        f" (spreads apart at {d.up + d.down:.0%} of the last {PLATEAU_SHARE:.0%} of the "
        f"episodes both ran; above at {d.above:.0%}, below at {d.below:.0%} "
        "of all of them)"
    )
    if d.length < a.fig.episodes and (finished := ended_short([mine, theirs], a.fig.episodes)):
        return f"{text} ({finished})"
    if d.length < a.fig.episodes:
        return f"{TOO_SHORT} ({d.length:,} of {a.fig.episodes:,} episodes); so far: {text}"
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
        runs = dict(zip(mine.seeds, mine.runs, strict=True))
        # the seeds with rows: a run not started yet has no value of its own to give
        ran = {s for s, r in runs.items() if len(a.points.get(r, {}).get("episode", ()))}
        seeds = {s: a.for_seed(s) for s in a.seeds if s in ran}
        end = _value(metric, mine.final if len(mine.episodes) else None)
        end_s = {s: _value(metric, x.arm(name).final) for s, x in seeds.items()}
        c1 = count1(a, name, configs[name])
        c1_s = {s: _pct(_c1(x, name, configs[name])) for s, x in seeds.items()}
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
        f"{DISTINGUISHED:.0%} of the last {PLATEAU_SHARE:.0%} of the episodes both ran, or, "
        "where those overlap, the spreads of each seed's mean over the episodes both ran "
        "(an arm that reaches the same end sooner).",
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
    if all(p.endswith(": no points") for p in parts):  # none started: once, not per seed
        return "no points" if parts else "-"
    return "; ".join(parts) or "-"
