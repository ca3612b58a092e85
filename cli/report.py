"""A reproduced figure's report: its curves smoothed as the thesis draws them, its
claims measured, and FIGURE.md / FIGURE.png / FIGURE.csv written.

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

import csv
import json
import math
from collections import Counter
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from cli.figures import FigureDef, arm_configs, control_of, is_macb, split_base
from cli.results import claims_record
from shared.config import TrainConfig

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


def _columns(points: Columns | list[dict[str, Any]]) -> Columns:
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
    cols = {run: _columns(p) for run, p in points.items()}
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


def _summary(a: Analysis, arm: ArmCurve) -> str:
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
        if not is_macb(configs[arm_def.name]):
            continue
        control = control_of(a.fig, arm_def.name)
        mine = a.arm(arm_def.name)
        if control is None:
            out.append((arm_def.name, None, _summary(a, mine), "-", "no control at its beta"))
            continue
        theirs = a.arm(control)
        if not len(mine.episodes) or not len(theirs.episodes):
            out.append((arm_def.name, control, _summary(a, mine), _summary(a, theirs), "no points"))
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
        out.append((arm_def.name, control, _summary(a, mine), _summary(a, theirs), verdict))
    return out


# ---------------------------------------------------------------- FIGURE.md
def _fmt_point(point: dict[str, Any]) -> str:
    return ", ".join(f"{k}={json.dumps(v)}" for k, v in point.items()) or "(the base)"


def _count1(a: Analysis, name: str, config: dict[str, Any]) -> float | None:
    """The arm's count-1 % at the figure's length; None without a point, or when the arm
    counts nothing (explore none or constant: no table, the 0 its rows carry is no
    measurement)."""
    if not is_macb({"explore": TrainConfig.model_fields["explore"].default, **config}):
        return None
    return a.arm(name).value_at(a.fig.episodes, "count1_pct")[0]


def _milestone(arm: ArmCurve, episode: int, metric: str) -> str:
    v, at = arm.value_at(episode, metric)
    if v is None or arm.length < episode:
        return "-" if v is None else f"({v:.0%} at {at:,})"
    return f"{v:.0%}"


def what_ran(runs: list[dict[str, Any]]) -> str:
    """The report's line on what the runs ran on, from each run's provenance (the
    learner's report, `live.provenance`): the precision as run, which may not be the one
    asked (bf16 on a CPU without it runs fp32), the CPUs and the code."""
    # provenance.reported(r), read here without it: shared.persist.provenance loads torch.
    starts = [(r.get("live") or {}).get("provenance") for r in runs]
    known = [s for s in starts if isinstance(s, dict)]
    if not known:
        return "- What ran: no run reported its provenance (docs/reliability.md)."
    ran = Counter(str((s.get("learner") or {}).get("precision")) for s in known)
    asked = sorted({str((s.get("learner") or {}).get("precision_asked")) for s in known})
    cpus = sorted({str((s.get("machine") or {}).get("cpu")) for s in known})
    commits = sorted({_commit(s.get("code") or {}) for s in known})
    precision = ", ".join(f"{p} on {n} run(s)" for p, n in sorted(ran.items()))
    line = f"- What ran (each run's provenance): learner precision {precision}"
    if set(ran) != set(asked):
        line += f" (**asked {', '.join(asked)}**: a CPU without native bf16 runs fp32)"
    line += f"; CPU {', '.join(cpus)}; code {', '.join(commits)}"
    if missing := len(starts) - len(known):
        line += f"; {missing} run(s) reported none"
    return line + "."


def _commit(code: dict[str, Any]) -> str:
    """A provenance's code as the report names it: the commit's first 12 digits, and
    whether tracked files differed from it."""
    commit = code.get("commit")
    if not commit:
        return "not a git checkout"
    return f"{str(commit)[:12]}{' (dirty)' if code.get('dirty') else ''}"


def markdown(a: Analysis, profile: str, out_png: str = "", command: str | None = None) -> str:
    """FIGURE.md: what ran, the definitions, each arm beside what the thesis reports for
    it, a verdict per claim, and each MACB arm against its control."""
    fig, exp = a.fig, a.experiment
    configs = arm_configs(fig)
    base, sets = split_base(configs)
    runs = exp.get("runs") or []
    if runs and "config" in runs[0]:  # what ran: --episodes cuts the files' length
        base["episodes"] = runs[0]["config"]["episodes"]
    base["profile"] = profile
    counts = ", ".join(f"{v} {k}" for k, v in (exp.get("counts") or {}).items())
    lengths = {arm.length for arm in a.arms.values()}
    window = sorted({arm.window for arm in a.arms.values()})
    lines = [
        f"# {fig.title}",
        "",
        f"Reproduced with `{command or f'macb reproduce {fig.name} --profile {profile}'}` on "
        f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC. The thesis: {fig.section} of "
        "`count-based-exploration-for-multi-agent-learning.txt`.",
        "",
        f"- Experiment: `{exp.get('id', '?')}` ({exp.get('name', '')}), status "
        f"{exp.get('status', '?')} ({counts or 'no runs'}).",
        f"- Profile `{profile}`; seeds {exp.get('seeds', [])}; the thesis ran 3 seeds of "
        f"{fig.episodes:,} episodes; these runs reached "
        f"{', '.join(f'{n:,}' for n in sorted(lengths))} episodes.",
        f"- Base config (every arm): {_fmt_point(base)}.",
        f"- Smoothing: centred moving average over {SMOOTH_SHARE:.0%} of each seed's "
        f"evaluation points (W = {', '.join(map(str, window))} point(s); the window shrinks "
        "symmetrically at the ends, which go unsmoothed; cumulative collisions are not "
        "smoothed), then the mean over seeds; band: mean +- one standard deviation over "
        "seeds (the thesis also draws a 75% confidence interval, not drawn here).",
        f"- Plateau: the mean over seeds and over the last {PLATEAU_SHARE:.0%} of the "
        f"points. Episodes to convergence: the first episode where the smoothed mean "
        f"reaches {CONVERGED:.0%} of the plateau, if the plateau is at least {LEARNED:.0%} "
        "(else: no plateau). The value at episode E: the mean over seeds and over the W "
        "points up to E (collisions: the count at E); final: the value at the last "
        "episode run.",
        "- Verdicts: reproduced / not reproduced by the stated rule; not run to that "
        "length when a run stopped short of the episodes the claim is about (the measured "
        "number is still given).",
    ]
    lines += [what_ran(runs)]
    if exp.get("wall_s"):  # local runs: their own clocks, over every start
        lines += [
            f"- Wall time: {exp['wall_s'] / 3600:.2f} h, the longest run's own clock (its "
            "`wall_s`, summed over its starts; runs of a group share it)."
        ]
    if fig.note:
        lines += [f"- {fig.note}"]
    if out_png:
        lines += ["", f"![{fig.name}]({out_png})"]
    lines += ["", "## Arms", ""]
    milestone_cols = [f"{fig.metric} at {e:,}" for e in fig.milestones]
    head = ["arm", "sets over the base", "seeds", "the thesis", "measured", *milestone_cols]
    if fig.kind == "table":
        head = ["arm", "sets over the base", "seeds", "the thesis (sr, c-1)", "measured (sr, c-1)"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for arm_def in fig.arms:
        arm = a.arm(arm_def.name)
        thesis = arm_def.thesis or "not in the thesis (control)"
        if fig.kind == "table":
            v, _ = arm.value_at(fig.episodes)
            c1 = _count1(a, arm_def.name, configs[arm_def.name])
            measured = "-" if v is None else f"{v:.0%}, " + ("-" if c1 is None else f"{c1:.0f}%")
            if v is not None and arm.length < fig.episodes:
                measured += f" (at {arm.length:,})"
        else:
            measured = arm.describe() if fig.metric != "collisions_cum" else _summary(a, arm)
        row = [
            arm_def.name,
            _fmt_point(sets[arm_def.name]),
            str(len(arm.runs)),
            thesis,
            measured,
            *(_milestone(arm, e, fig.metric) for e in fig.milestones),
        ]
        lines.append("| " + " | ".join(row) + " |")
    lines += [
        "",
        "## Claims",
        "",
        "| # | the thesis says | where | the thesis | measured | verdict |",
    ]
    lines.append("|---|---|---|---|---|---|")
    verdicts = claim_verdicts(a)
    for i, (claim, text, verdict) in enumerate(verdicts, 1):
        lines.append(
            f"| {i} | {claim.text} | {claim.where} | {claim.thesis} | {text} | **{verdict}** |"
        )
    tally = {v: sum(1 for *_, x in verdicts if x == v) for v in (REPRODUCED, NOT_REPRODUCED)}
    too_short = len(verdicts) - sum(tally.values())
    lines += [
        "",
        f"{tally[REPRODUCED]} reproduced, {tally[NOT_REPRODUCED]} not reproduced, "
        f"{too_short} not run to that length.",
        "",
        "## Against the control",
        "",
        "The control is the constant bonus with the same beta and reward, no counting: a "
        "count-bonus arm that does not beat it owes its effect to the reward shift, not "
        "to counting. Better: fewer episodes to convergence (then a higher final "
        "success)" + ("; fewer collisions" if fig.metric == "collisions_cum" else "") + ".",
        "",
        "| MACB arm | control | MACB measured | control measured | verdict |",
        "|---|---|---|---|---|",
    ]
    for name, control, mine, theirs, verdict in control_verdicts(a):
        lines.append(f"| {name} | {control or '-'} | {mine} | {theirs} | **{verdict}** |")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------- FIGURE.png
LABELS = {"success_rate": "success rate", "collisions_cum": "cumulative collisions"}


def legend_text(arm: ArmCurve) -> str:
    n = len(arm.runs)
    return f"{arm.name} ({n} seed{'' if n == 1 else 's'})"


def draw(a: Analysis, profile: str) -> tuple[Any, list[str]]:
    """The figure (Agg) and its legend texts: curves overlaid, or for a table figure a
    grid of cells (its "legend": an entry per arm drawn as a cell)."""
    from matplotlib.figure import Figure

    if a.fig.kind == "table":
        return _draw_table(a, profile)
    from services.api.plot import palette

    fig = Figure(figsize=(7.2, 4.6), dpi=120)
    ax = fig.subplots()
    metric = a.fig.metric
    drawn = [arm for arm in a.arms.values() if len(arm.episodes)]
    for arm, color in zip(drawn, palette(len(drawn)), strict=True):
        m, s = arm.mean[metric], arm.std[metric]
        dashed = "control" in arm.name
        ax.plot(
            arm.episodes, m, lw=1.5, color=color, ls="--" if dashed else "-", label=legend_text(arm)
        )
        ax.fill_between(arm.episodes, m - s, m + s, color=color, alpha=0.18, lw=0)
    ax.set_xlabel("training episodes")
    ax.set_ylabel(LABELS.get(metric, metric))
    if metric == "success_rate":
        ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    window = sorted({arm.window for arm in drawn})
    ax.set_title(
        f"{a.fig.title} (profile {profile})\nsmoothed (moving average, "
        f"{'/'.join(map(str, window)) or '-'} points), mean over seeds, band ± one std",
        fontsize=9,
    )
    legend: list[str] = []
    if drawn:
        legend = [t.get_text() for t in ax.legend(fontsize=7, loc="best").get_texts()]
    else:
        ax.text(0.5, 0.5, "no metric points stored", ha="center", transform=ax.transAxes)
    fig.tight_layout()
    return fig, legend


def _draw_table(a: Analysis, profile: str) -> tuple[Any, list[str]]:
    """Rows k (and beta 0, the controls), columns beta; colour = measured success, text
    = measured and the thesis's (sr, c-1)."""
    from matplotlib.figure import Figure

    rows = list(dict.fromkeys(d.row for d in a.fig.arms))
    cols = sorted({d.col for d in a.fig.arms}, key=float)
    grid = np.full((len(rows), len(cols)), np.nan)
    fig = Figure(figsize=(7.6, 4.8), dpi=120)
    ax = fig.subplots()
    texts = {}
    configs = arm_configs(a.fig)
    for d in a.fig.arms:
        arm = a.arm(d.name)
        v, _ = arm.value_at(a.fig.episodes)
        c1 = _count1(a, d.name, configs[d.name])
        i, j = rows.index(d.row), cols.index(d.col)
        if v is not None:
            grid[i, j] = v
        measured = "-" if v is None else f"{v:.0%}" + ("" if c1 is None else f", {c1:.0f}%")
        texts[(i, j)] = f"{measured}\n(thesis {d.thesis or 'none: control'})"
    ax.imshow(np.ma.masked_invalid(grid), cmap="viridis", vmin=0, vmax=1, aspect="auto")
    for (i, j), t in texts.items():
        ax.text(
            j,
            i,
            t,
            ha="center",
            va="center",
            fontsize=7,
            color="white" if not np.isnan(grid[i, j]) and grid[i, j] < 0.6 else "black",
        )
    ax.set_xticks(range(len(cols)), [f"β={c}" for c in cols])
    names = {"-": "no bonus", "constant": "constant\n(control)"}
    ax.set_yticks(range(len(rows)), [f"k={r}" if r.isdigit() else names.get(r, r) for r in rows])
    lengths = sorted({arm.length for arm in a.arms.values()})
    ax.set_title(
        f"{a.fig.title}\nprofile {profile}; measured success (smoothed, mean over seeds) "
        f"and count-1 at {a.fig.episodes:,} or the last episode run "
        f"({'/'.join(f'{n:,}' for n in lengths)})",
        fontsize=8,
    )
    fig.tight_layout()
    return fig, [legend_text(a.arm(d.name)) for d in a.fig.arms if d.name in a.arms]


def write_png(a: Analysis, profile: str, path: Path) -> Path:
    """FIGURE.png; its `Legend` text chunk (JSON) lists the legend entries, as
    `macb plot`'s PNGs do, so a test or a script can tell which arms it shows."""
    fig, legend = draw(a, profile)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, metadata={"Legend": json.dumps(legend)})
    return path


def write_csv(exp: dict[str, Any], points: dict[str, Columns | list], path: Path) -> Path:
    """FIGURE.csv: every point of every run, only the columns the report reads."""
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for r in exp["runs"]:
            c = _columns(points.get(r["id"], []))
            fields = [c[k] for k in CSV_COLUMNS[3:]]
            for i in range(len(c["episode"])):
                w.writerow([r["arm"], r["seed"], r["id"], *(_cell(x[i]) for x in fields)])
    return path


def _cell(x: Any) -> Any:
    """A CSV cell: integral values without '.0', a missing value empty."""
    x = float(x)
    if math.isnan(x):
        return ""
    return int(x) if x.is_integer() else x


def write_report(
    a: Analysis,
    points: dict[str, Columns | list],
    profile: str,
    out: Path,
    command: str | None = None,
) -> list[Path]:
    """FIGURE.png, FIGURE.md, FIGURE.csv and FIGURE-claims.json (for `macb results`) in out/."""
    out.mkdir(parents=True, exist_ok=True)
    name = a.fig.name
    png = write_png(a, profile, out / f"{name}.png")
    md = out / f"{name}.md"
    md.write_text(markdown(a, profile, png.name, command))
    lengths = [arm.length for arm in a.arms.values() if arm.runs]
    record = claims_record(
        name, profile, claim_verdicts(a), min(lengths, default=0), a.fig.episodes,
        list(a.experiment.get("seeds") or []),
    )  # fmt: skip
    claims = out / f"{name}-claims.json"
    claims.write_text(json.dumps(record, indent=1) + "\n")
    return [png, md, write_csv(a.experiment, points, out / f"{name}.csv"), claims]
