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
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cli.reproduce.defs import FigureDef
from cli.reproduce.experiments import counts

SMOOTH_SHARE = 0.02
PLATEAU_SHARE = 0.10
LEARNED = 0.5
CONVERGED = 0.9
METRICS = ("success_rate", "collisions_cum", "count1_pct")
UNSMOOTHED = ("collisions_cum",)  # cumulative: smooth by construction
CSV_COLUMNS = ("arm", "seed", "run", "episode", "env_steps", *METRICS, "eval_return")
# Read besides the CSV's: what a counting arm paid (cli/reproduce/why.py) and each run's
# own clock (cli/reproduce/status.py).
LOADED = (*CSV_COLUMNS[4:], "bonus_mean", "bonus_std", "wall_s")
BANDS = {
    "std": "mean +- one standard deviation over seeds",
    "ci75": "the 75% confidence interval of the mean over seeds (bootstrap: the 12.5th to "
    "87.5th percentile of the mean over every resample of the seeds with replacement, "
    "as seaborn's `ci=75` draws it)",
}
EXACT_BOOTSTRAP_SEEDS = 4  # up to n seeds every one of the n**n resamples; beyond, 1,000


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
    smoothed: dict[str, np.ndarray] = field(default_factory=dict)  # (seeds, points) each
    band_kind: str = "std"  # the band drawn around the mean: a key of BANDS
    stopped: dict[int, int] = field(default_factory=dict)  # seed -> where early_stop ended it

    def ended_by_rule(self, needs: int) -> bool:
        """Every seed that stops short of `needs` episodes was ended by its `early_stop`
        rule (a finished run, not one cut short)."""
        short = [seed for seed, t in self.traces.items() if int(t[-1, 0]) < needs]
        return all(seed in self.stopped for seed in short) and bool(self.stopped)

    def band(self, metric: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) of the band drawn around the mean curve, at each episode."""
        metric = metric or self.metric
        m = self.mean.get(metric, np.zeros(0))
        if self.band_kind == "ci75" and metric in self.smoothed:
            return bootstrap_ci(self.smoothed[metric], 75.0)
        s = self.std.get(metric, np.zeros(0))
        return m - s, m + s

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
    for f in LOADED:
        out[f] = np.array([_num(p.get(f)) for _, p in rows], dtype=float)
    # the episode whose row says the run's early_stop rule ended it there (none or one)
    stops = [e for e, p in rows if isinstance(p.get("stop_reason"), str) and p["stop_reason"]]
    out["stop"] = np.array(stops, dtype=np.int64)
    return out


def as_columns(points: Columns | list[dict[str, Any]]) -> Columns:
    return columns(points) if isinstance(points, list) else points


def bootstrap_ci(stack: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """The percentile bootstrap interval of the mean over the rows of `stack` (seeds x
    points), at each point: exact (every resample of the n seeds with replacement) up to
    EXACT_BOOTSTRAP_SEEDS seeds, else 1,000 resamples of a fixed seed, so a page rebuilt
    from the same runs draws the same band."""
    n = len(stack)
    if n == 0 or not stack.shape[1]:
        return np.zeros(0), np.zeros(0)
    if n <= EXACT_BOOTSTRAP_SEEDS:
        idx = np.stack(np.meshgrid(*[np.arange(n)] * n, indexing="ij"), -1).reshape(-1, n)
    else:
        idx = np.random.default_rng(0).integers(0, n, size=(1000, n))
    q = [50 - level / 2, 50 + level / 2]
    lo, hi = np.empty(stack.shape[1]), np.empty(stack.shape[1])
    for a in range(0, stack.shape[1], 4096):  # bounded memory on 50,000-point curves
        means = stack[:, a : a + 4096][idx].mean(axis=1)
        lo[a : a + 4096], hi[a : a + 4096] = np.percentile(means, q, axis=0)
    return lo, hi


def arm_curve(
    name: str,
    runs: list[dict[str, Any]],
    points: dict[str, Columns],
    metric: str,
    only: np.ndarray | None = None,
    band: str = "std",
) -> ArmCurve:
    """Smooth each seed's curves, then mean and std over seeds at the shared episodes
    (or at `only`'s, those of the arm this is one seed of)."""
    empty = columns([])
    series = [points.get(r["id"], empty) for r in runs]
    shared = np.arange(0)
    if series:
        shared = series[0]["episode"]
        for s in series[1:]:
            shared = np.intersect1d(shared, s["episode"])
    if only is not None:
        shared = np.intersect1d(shared, only)
    mean, std, raw, stacks = {}, {}, {}, {}
    for m in METRICS:
        rows, smoothed = [], []
        for s in series:
            vals = np.nan_to_num(s[m][np.isin(s["episode"], shared)])
            rows.append(vals)
            smoothed.append(vals if m in UNSMOOTHED else smooth(vals))
        if not len(shared):
            mean[m] = std[m] = raw[m] = np.zeros(0)
            continue
        stacks[m] = np.stack(smoothed)
        mean[m], std[m] = stacks[m].mean(axis=0), stacks[m].std(axis=0)
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
        smoothed=stacks,
        band_kind=band,
        stopped={r["seed"]: int(s["stop"][0]) for r, s in zip(runs, series) if len(s["stop"])},
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
    points: dict[str, Columns] = field(default_factory=dict)  # per run
    _seeds: dict[int, Analysis] = field(default_factory=dict, repr=False)

    def arm(self, name: str) -> ArmCurve:
        return self.arms[name]

    @property
    def seeds(self) -> list[int]:
        return list(self.experiment.get("seeds") or [])

    def for_seed(self, seed: int) -> Analysis:
        """The figure as one seed ran it: each arm's run of that seed alone, at the
        episodes its arm's mean is taken at (so the mean of the seeds' values at an
        episode is the arm's value there)."""
        if seed not in self._seeds:
            arms = {
                n: arm_curve(
                    n,
                    [r for r in self.experiment["runs"] if r["arm"] == n and r["seed"] == seed],
                    self.points,
                    self.fig.metric,
                    only=arm.episodes,
                )
                for n, arm in self.arms.items()
            }
            self._seeds[seed] = Analysis(self.fig, arms, self.experiment, self.points)
        return self._seeds[seed]


def analyse(
    fig: FigureDef, exp: dict[str, Any], points: Mapping[str, Columns | list[dict[str, Any]]]
) -> Analysis:
    """The figure's arms from an experiment (GET /experiments/{id}) and its points (per
    run: `columns`, or the points as the API serves them)."""
    cols = {run: as_columns(p) for run, p in points.items()}
    by_arm: dict[str, list[dict]] = {a.name: [] for a in fig.arms}
    for r in exp["runs"]:
        by_arm.setdefault(r["arm"], []).append(r)
    arms = {n: arm_curve(n, runs, cols, fig.metric, band=fig.band) for n, runs in by_arm.items()}
    return Analysis(fig, arms, exp, cols)


# ---------------------------------------------------------------- verdicts
REPRODUCED, NOT_REPRODUCED, TOO_SHORT = "reproduced", "not reproduced", "not run to that length"


def ended_short(arms: list[ArmCurve], needs: int) -> str | None:
    """What to say when every run of `arms` that stops short of `needs` episodes was
    ended there by its `early_stop` rule: finished, so a verdict about `needs` is given
    on what they ran (None: some run was merely cut short, or none was ended)."""
    short = [arm for arm in arms if arm.length < needs]
    if not short or not all(arm.ended_by_rule(needs) for arm in short):
        return None
    ends = sorted({e for arm in arms for e in arm.stopped.values()})
    return (
        f"runs ended by their early_stop rule at episode(s) "
        f"{', '.join(f'{e:,}' for e in ends)}, short of {needs:,}: finished"
    )


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
        finished = ended_short([a.arm(n) for n in check.arms()], check.needs)
        if length < check.needs and finished:
            verdict = REPRODUCED if ok else NOT_REPRODUCED
            text += f" ({finished})"
        elif length < check.needs:
            verdict = TOO_SHORT
            text += f" (runs reached {length:,} of {check.needs:,} episodes)"
        else:
            verdict = REPRODUCED if ok else NOT_REPRODUCED
        out.append((claim, text, verdict))
    return out


def count1(a: Analysis, name: str, config: dict[str, Any]) -> float | None:
    """The arm's count-1 % at the figure's length; None without a point, or when the arm
    counts nothing (explore none or constant: no table, the 0 its rows carry is no
    measurement)."""
    if not counts(config):
        return None
    return a.arm(name).value_at(a.fig.episodes, "count1_pct")[0]
