"""A reproduced figure analysed: its curves smoothed as the thesis draws them, each
arm's mean and spread over seeds, its claims measured, each counting arm against its
control (cli/reproduce/render.py and plot.py write the page from it).

The definitions, stated once here and in every FIGURE.md:

- Smoothing: each seed's curve is a centred moving average over `SMOOTH_SHARE` of its
  evaluation points (an odd window of W >= 1 points), the window shrunk symmetrically
  at the ends, so a straight line stays straight (the end points go unsmoothed). The
  thesis smooths too (§6 l.373, with SciPy, its filter not given); a moving average is
  the plainest filter with a stated width. Cumulative collisions are not smoothed.
- Per arm: the mean over seeds of the smoothed curves at each episode all seeds
  reached, and their standard deviation (ddof 0; the band drawn is mean +- std).
- Plateau: the mean over seeds and over the last `PLATEAU_SHARE` of points.
- Episodes to convergence: the first episode where the smoothed mean reaches 90% of the
  plateau, if the plateau is at least `LEARNED` (below it: "no plateau").
- The value at episode E (success, count-1): the mean over seeds and over the last W
  points up to E (the smoothing window, trailing: the end of a run has no points
  after it); cumulative collisions: the value at E.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cli.reproduce.defs import FigureDef
from cli.reproduce.experiments import arm_configs, control_of, counts

SMOOTH_SHARE = 0.02
PLATEAU_SHARE = 0.10
LEARNED = 0.5
CONVERGED = 0.9
METRICS = ("success_rate", "collisions_cum", "count1_pct")
UNSMOOTHED = ("collisions_cum",)  # cumulative: smooth by construction
CSV_COLUMNS = ("arm", "seed", "run", "episode", "env_steps", *METRICS, "eval_return")


def smooth(values: np.ndarray, share: float = SMOOTH_SHARE) -> np.ndarray:
    """Centred moving average over `share` of the points (an odd window, >= 1), shrunk
    symmetrically near the ends: point i is the mean of the points within
    min(half a window, i, n-1-i) of it, so a linear trend passes unchanged."""
    n = len(values)
    half = max(0, round(share * n) // 2)
    if n == 0 or half == 0:
        return values.astype(float)
    c = np.concatenate([[0.0], np.cumsum(values, dtype=float)])
    i = np.arange(n)
    h = np.minimum(half, np.minimum(i, n - 1 - i))
    return (c[i + h + 1] - c[i - h]) / (2 * h + 1)


def window_points(n: int, share: float = SMOOTH_SHARE) -> int:
    """The smoothing window, in evaluation points, for a curve of n points."""
    return 2 * max(0, round(share * n) // 2) + 1


@dataclass
class ArmCurve:
    """One arm over its seeds: per metric, the mean of the smoothed seed curves and
    their std, at the episodes every seed reached."""

    name: str
    runs: list[str]
    seeds: list[int]
    episodes: np.ndarray
    mean: dict[str, np.ndarray]  # of the smoothed seed curves
    std: dict[str, np.ndarray]
    raw: dict[str, np.ndarray]  # the mean over seeds of the points as stored
    metric: str = "success_rate"
    window: int = 1
    # per seed, every point the run stored as (episode, success, return, collisions)
    # rows: two arms whose traces agree as far as both go are the same runs
    traces: dict[int, np.ndarray] = field(default_factory=dict)

    @property
    def length(self) -> int:
        """The last training episode every seed reached (0: no points)."""
        return int(self.episodes[-1]) if len(self.episodes) else 0

    def curve(self, metric: str | None = None) -> np.ndarray:
        return self.mean.get(metric or self.metric, np.zeros(0))

    @property
    def final(self) -> float:
        """The value at the last episode every seed reached."""
        v, _ = self.value_at(self.length)
        return math.nan if v is None else v

    @property
    def peak(self) -> float:
        c = self.curve()
        return float(c.max()) if len(c) else math.nan

    @property
    def plateau(self) -> float:
        c = self.raw.get(self.metric, np.zeros(0))
        if not len(c):
            return math.nan
        return float(c[-max(1, round(PLATEAU_SHARE * len(c))) :].mean())

    def first_reaching(self, target: float) -> int | None:
        c = self.curve()
        hit = np.flatnonzero(c >= target)
        return int(self.episodes[hit[0]]) if len(hit) else None

    @property
    def converged(self) -> int | None:
        p = self.plateau
        if not (p >= LEARNED):
            return None
        return self.first_reaching(CONVERGED * p)

    def value_at(self, episode: int, metric: str | None = None) -> tuple[float | None, int]:
        """At the last point at or before `episode`: the mean over the W points up to it
        (the value there, for an unsmoothed metric), and that point's episode."""
        metric = metric or self.metric
        c = self.raw.get(metric, np.zeros(0))
        idx = int(np.searchsorted(self.episodes, episode, side="right")) - 1
        if idx < 0 or not len(c):
            return None, 0
        w = 1 if metric in UNSMOOTHED else self.window
        return float(c[max(0, idx - w + 1) : idx + 1].mean()), int(self.episodes[idx])

    def describe(self) -> str:
        if not len(self.episodes):
            return "no points"
        conv = self.converged
        if conv is None:
            return f"plateau {self.plateau:.0%} (under {LEARNED:.0%}: none reached), " + (
                f"{self.length:,} episodes"
            )
        return f"plateau {self.plateau:.0%}, converged at {conv:,} of {self.length:,} episodes"


Columns = dict[str, np.ndarray]  # one run's points: a column per CSV_COLUMNS field


def columns(points: list[dict[str, Any]]) -> Columns:
    """A run's points (as the API serves them) as columns, in episode order, without
    the fields the report does not read: a 50,000-episode figure's points as dicts would
    take gigabytes, as columns a few megabytes per run. A repeated episode is kept once."""
    rows = sorted({int(p["episode"]): p for p in points if "episode" in p}.items())
    out = {"episode": np.array([e for e, _ in rows], dtype=np.int64)}
    for f in CSV_COLUMNS[4:]:
        out[f] = np.array([_num(p.get(f)) for _, p in rows], dtype=float)
    return out


def as_columns(points: Columns | list[dict[str, Any]]) -> Columns:
    return columns(points) if isinstance(points, list) else points


def arm_curve(
    name: str, runs: list[dict[str, Any]], points: dict[str, Columns], metric: str
) -> ArmCurve:
    """Smooth each seed's curves, then mean and std over seeds at the shared episodes."""
    empty = columns([])
    series = [points.get(r["id"], empty) for r in runs]
    shared = np.arange(0)
    if series:
        shared = series[0]["episode"]
        for s in series[1:]:
            shared = np.intersect1d(shared, s["episode"])
    mean, std, raw = {}, {}, {}
    for m in METRICS:
        rows, smoothed = [], []
        for s in series:
            vals = np.nan_to_num(s[m][np.isin(s["episode"], shared)])
            rows.append(vals)
            smoothed.append(vals if m in UNSMOOTHED else smooth(vals))
        if not len(shared):
            mean[m] = std[m] = raw[m] = np.zeros(0)
            continue
        mean[m], std[m] = np.stack(smoothed).mean(axis=0), np.stack(smoothed).std(axis=0)
        raw[m] = np.stack(rows).mean(axis=0)
    return ArmCurve(
        name=name,
        runs=[r["id"] for r in runs],
        seeds=[r["seed"] for r in runs],
        episodes=shared.astype(int),
        mean=mean,
        std=std,
        raw=raw,
        metric=metric,
        window=window_points(len(shared)),
        traces={r["seed"]: _trace(s) for r, s in zip(runs, series) if len(s["episode"])},
    )


TRACED = ("episode", "success_rate", "eval_return", "collisions_cum")


def _trace(points: Columns) -> np.ndarray:
    return np.stack([np.asarray(points[f], dtype=float) for f in TRACED], axis=1)


def same_runs(mine: ArmCurve, theirs: ArmCurve) -> bool:
    """Every seed of both arms gave the same points as far as both runs went (one may
    have been stopped sooner): the same runs, not two that happen to end alike."""
    if not mine.traces or mine.traces.keys() != theirs.traces.keys():
        return False
    for seed, a in mine.traces.items():
        b = theirs.traces[seed]
        n = min(len(a), len(b))
        if n == 0 or not np.array_equal(a[:n], b[:n], equal_nan=True):
            return False
    return True


def _num(x: Any) -> float:
    return float(x) if isinstance(x, int | float) and not isinstance(x, bool) else math.nan


@dataclass
class Analysis:
    fig: FigureDef
    arms: dict[str, ArmCurve]
    experiment: dict[str, Any] = field(default_factory=dict)

    def arm(self, name: str) -> ArmCurve:
        return self.arms[name]


def analyse(
    fig: FigureDef, exp: dict[str, Any], points: dict[str, Columns | list[dict[str, Any]]]
) -> Analysis:
    """The figure's arms from an experiment (GET /experiments/{id}) and its points (per
    run: `columns`, or the points as the API serves them)."""
    cols = {run: as_columns(p) for run, p in points.items()}
    by_arm: dict[str, list[dict]] = {a.name: [] for a in fig.arms}
    for r in exp["runs"]:
        by_arm.setdefault(r["arm"], []).append(r)
    arms = {n: arm_curve(n, runs, cols, fig.metric) for n, runs in by_arm.items()}
    return Analysis(fig, arms, exp)


# ---------------------------------------------------------------- verdicts
REPRODUCED, NOT_REPRODUCED, TOO_SHORT = "reproduced", "not reproduced", "not run to that length"


def claim_verdicts(a: Analysis) -> list[tuple[Any, str, str]]:
    """(claim, measured text, verdict) per claim of the figure."""
    out = []
    for claim in a.fig.claims:
        check = claim.check
        length = min((a.arm(n).length for n in check.arms()), default=0)
        if length == 0:
            out.append((claim, "no points", TOO_SHORT))
            continue
        text, ok = check.measure(a)
        if length < check.needs:
            verdict = TOO_SHORT
            text += f" (runs reached {length:,} of {check.needs:,} episodes)"
        else:
            verdict = REPRODUCED if ok else NOT_REPRODUCED
        out.append((claim, text, verdict))
    return out


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
    out = []
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
        if same_runs(mine, theirs):
            verdict = f"the same runs as the control, point for point: {SAME_RUNS}"
        elif _score(a, mine) < _score(a, theirs):
            verdict = "beats the control"
        else:
            verdict = "does not beat the control"
        length = min(mine.length, theirs.length)
        if length < a.fig.episodes:
            verdict += f" (at {length:,} of {a.fig.episodes:,} episodes)"
        out.append((arm_def.name, control, summary(a, mine), summary(a, theirs), verdict))
    return out


def count1(a: Analysis, name: str, config: dict[str, Any]) -> float | None:
    """The arm's count-1 % at the figure's length; None without a point, or when the arm
    counts nothing (explore none or constant: no table, the 0 its rows carry is no
    measurement)."""
    if not counts(config):
        return None
    return a.arm(name).value_at(a.fig.episodes, "count1_pct")[0]
