"""FIGURE.png: a figure's arms overlaid as the thesis draws them (smoothed, the mean
over seeds, a band), or for a table figure a grid of cells.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from cli.reproduce.analysis import Analysis, ArmCurve, count1
from cli.reproduce.experiments import arm_configs

LABELS = {"success_rate": "success rate", "collisions_cum": "cumulative collisions"}
BAND_TITLES = {"std": "band ± one std", "ci75": "band: 75% CI over seeds (bootstrap)"}


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
        m, (lo, hi) = arm.mean[metric], arm.band(metric)
        dashed = "control" in arm.name
        ax.plot(
            arm.episodes, m, lw=1.5, color=color, ls="--" if dashed else "-", label=legend_text(arm)
        )
        ax.fill_between(arm.episodes, lo, hi, color=color, alpha=0.18, lw=0)
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
