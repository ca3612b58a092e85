"""FIGURE.png: a figure's arms overlaid as the thesis draws them (smoothed, the mean
over seeds, a band), with the values the thesis claims at an episode marked beside
them, or for a table figure a grid of cells.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from cli.reproduce.analysis import Analysis, ArmCurve, count1
from cli.reproduce.claims import ValueAt
from cli.reproduce.experiments import arm_configs

LABELS = {"success_rate": "success rate", "collisions_cum": "cumulative collisions"}
BAND_TITLES = {"std": "band ± one std", "ci75": "band: 75% CI over seeds (bootstrap)"}


def legend_text(arm: ArmCurve) -> str:
    n = len(arm.runs)
    return f"{arm.name} ({n} seed{'' if n == 1 else 's'})"


def figure_colors(a: Analysis) -> dict[str, str]:
    """Each arm's colour by its place among the arms the experiment runs, points or not
    (as the dashboard colours an experiment's arms): the PNG and `macb view` draw it so,
    and an arm keeps its colour when an earlier one gets its first points."""
    from services.api.plot import arm_colors

    return arm_colors([arm.name for arm in a.arms.values() if arm.runs])


def draw(a: Analysis, profile: str) -> tuple[Any, list[str]]:
    """The figure (Agg) and its legend texts: curves overlaid, or for a table figure a
    grid of cells (its "legend": an entry per arm drawn as a cell)."""
    from matplotlib.figure import Figure

    if a.fig.kind == "table":
        return _draw_table(a, profile)
    fig = Figure(figsize=(7.2, 4.6), dpi=120)
    ax = fig.subplots()
    metric = a.fig.metric
    drawn = [arm for arm in a.arms.values() if len(arm.episodes)]
    colors = figure_colors(a)
    for arm in drawn:
        m, (lo, hi) = arm.mean[metric], arm.band(metric)
        dashed = "control" in arm.name
        color = colors[arm.name]
        ax.plot(
            arm.episodes, m, lw=1.5, color=color, ls="--" if dashed else "-", label=legend_text(arm)
        )
        ax.fill_between(arm.episodes, lo, hi, color=color, alpha=0.18, lw=0)
    planned = planned_episodes(a)
    if drawn and planned > max(int(arm.episodes[-1]) for arm in drawn):
        ax.set_xlim(-0.02 * planned, 1.02 * planned)  # the whole length: how far it got
    _draw_thesis_values(ax, a, colors)
    ax.set_xlabel("training episodes")
    ax.set_ylabel(LABELS.get(metric, metric))
    if metric == "success_rate":
        ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    window = sorted({arm.window for arm in drawn})
    ax.set_title(
        f"{a.fig.title} (profile {profile})\nsmoothed (moving average, "
        f"{'/'.join(map(str, window)) or '-'} points), mean over seeds, {BAND_TITLES[a.fig.band]}",
        fontsize=9,
    )
    legend: list[str] = []
    if drawn:
        legend = [t.get_text() for t in ax.legend(fontsize=7, loc="best").get_texts()]
    else:
        ax.text(0.5, 0.5, "no metric points stored", ha="center", transform=ax.transAxes)
    fig.tight_layout()
    return fig, legend


def planned_episodes(a: Analysis) -> int:
    """The episodes the runs were started for (their configs'), 0 when unknown."""
    runs = a.experiment.get("runs") or []
    return max((int((r.get("config") or {}).get("episodes") or 0) for r in runs), default=0)


def thesis_marks(a: Analysis) -> list[tuple[int, Any, ValueAt]]:
    """The claims the plot marks, numbered as on the page: each value a claim states at
    an episode (`ValueAt`) of a drawn success-rate arm whose runs were started to reach
    that episode (a short run's axis is not stretched to the thesis's length)."""
    if a.fig.kind == "table" or a.fig.metric != "success_rate":
        return []
    planned = planned_episodes(a)
    drawn = {name for name, arm in a.arms.items() if len(arm.episodes)}
    return [
        (n, claim, claim.check)
        for n, claim in enumerate(a.fig.claims, 1)
        if isinstance(claim.check, ValueAt)
        and claim.check.arm in drawn
        and claim.check.episode <= planned
    ]


def _draw_thesis_values(ax: Any, a: Analysis, colors: dict[str, Any]) -> None:
    """`thesis_marks` as the thesis states them: a hollow diamond with the claim's
    accepted range as its bar, in its arm's colour."""
    for n, claim, check in thesis_marks(a):
        mid, half = (check.lo + check.hi) / 2, (check.hi - check.lo) / 2
        color = colors[check.arm]
        ax.errorbar(
            [check.episode], [mid], yerr=[[half], [half]], fmt="D", mfc="white", mec=color,
            ecolor=color, ms=6, capsize=3, lw=1.2, zorder=5,
        )  # fmt: skip
        ax.annotate(
            f"thesis, claim {n}: {claim.thesis}",
            (check.episode, mid),
            xytext=(-6, 0),
            textcoords="offset points",
            ha="right",
            va="center",
            fontsize=6.5,
            color=color,
        )


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
        c1 = count1(a, d.name, configs[d.name])
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
