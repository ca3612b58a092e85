"""The thesis-style figure: a metric against training episodes, every arm overlaid on one
chart, each its mean over seeds with a band (mean +- one standard deviation), from
stored metrics. The PNG also carries its legend texts (a `Legend` text chunk, JSON), so
a figure can be checked, or its arms listed, without looking at it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from matplotlib.figure import Figure

LABELS = {
    "success_rate": "success rate",
    "count1_pct": "count-1 % (keys seen once)",
    "sampled_count1_pct": "sampled rows with n = 1 (%)",
    "steps_per_sec": "env steps / s",
    "eval_return": "evaluation return",
    "collisions_cum": "cumulative collisions",
}


def legend_text(curve: dict[str, Any]) -> str:
    """An arm's legend entry: its name and how many seeds it has."""
    seeds = len(curve["runs"])
    return f"{curve.get('name') or curve['label']} ({seeds} seed{'' if seeds == 1 else 's'})"


def draw_curves(curves: dict[str, Any], metric: str) -> Figure:
    """The figure (Agg, not shown): one mean line and band per arm with points stored
    (an arm that counts nothing has none of the count metrics: `views.curves_of`)."""
    from matplotlib.figure import Figure

    groups = curves["metrics"].get(metric, [])
    fig = Figure(figsize=(6.4, 4.2), dpi=120)
    ax = fig.subplots()
    colors = arm_colors(arm_order(curves))
    for g in groups:
        if not g["episode"]:
            continue
        color = colors[g.get("name") or g["label"]]
        ax.plot(g["episode"], g["mean"], lw=1.6, color=color, label=legend_text(g))
        ax.fill_between(g["episode"], g["lo"], g["hi"], color=color, alpha=0.2, lw=0)
    ax.set_xlabel("training episodes")
    ax.set_ylabel(LABELS.get(metric, metric))
    if metric == "success_rate":
        ax.set_ylim(-0.02, 1.02)
    elif metric.endswith("_pct"):  # a percentage: 0-100, however wide a band is
        ax.set_ylim(-2, 102)
    ax.grid(alpha=0.3)
    subtitle = "(mean over seeds, band: ± one standard deviation)"
    ax.set_title(f"{curves['name']}\n{subtitle}", fontsize=10)
    if any(g["episode"] for g in groups):
        ax.legend(fontsize=8, loc="best")
    else:
        ax.text(0.5, 0.5, "no metric points stored yet", ha="center", transform=ax.transAxes)
    fig.tight_layout()
    return fig


# matplotlib's tab10 and tab20, as hex: the PNGs and the pages (charts.js holds the same
# lists; tests/test_plot_colors.py checks all three agree).
TAB10 = (
    "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd",
    "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf",
)  # fmt: skip
TAB20 = (
    "#1f77b4", "#aec7e8", "#ff7f0e", "#ffbb78", "#2ca02c", "#98df8a", "#d62728",
    "#ff9896", "#9467bd", "#c5b0d5", "#8c564b", "#c49c94", "#e377c2", "#f7b6d2",
    "#7f7f7f", "#c7c7c7", "#bcbd22", "#dbdb8d", "#17becf", "#9edae5",
)  # fmt: skip


def palette(n: int) -> list[str]:
    """n colours: tab10's up to 10 arms, tab20's (paired shades) beyond, then repeating."""
    colors = TAB10 if n <= 10 else TAB20
    return [colors[i % len(colors)] for i in range(n)]


def arm_colors(names: list[str]) -> dict[str, str]:
    """Each arm's colour, by its place among `names` (the arms in the experiment's order),
    the same in every chart of it whichever arms a chart draws."""
    return dict(zip(names, palette(len(names)), strict=True))


def arm_order(curves: dict[str, Any]) -> list[str]:
    """The experiment's arms in order: the success rate's (every arm has one), then any
    other metric's arms it lacks."""
    metrics = curves["metrics"]
    names: list[str] = []
    for metric in ("success_rate", *metrics):
        for g in metrics.get(metric, []):
            if (name := g.get("name") or g["label"]) not in names:
                names.append(name)
    return names


def figure_legend(fig: Figure) -> list[str]:
    """The legend texts of a figure drawn by `draw_curves` ([] without a legend)."""
    legend = fig.axes[0].get_legend()
    return [t.get_text() for t in legend.get_texts()] if legend else []


class PlotFormatError(ValueError):
    """An output file whose suffix names a format matplotlib does not write."""


def plot_curves(curves: dict[str, Any], metric: str, out: Path) -> Path:
    """Draw and write the figure in the format its suffix names (matplotlib's: png, svg,
    pdf, ...; none: png; PlotFormatError, nothing made, for one it lacks); a PNG's
    `Legend` text chunk lists the legend entries (the others have no place for it)."""
    out = Path(out)
    out = out if out.suffix else out.with_suffix(".png")
    fig = draw_curves(curves, metric)
    writes = fig.canvas.get_supported_filetypes()
    if out.suffix[1:].lower() not in writes:
        raise PlotFormatError(
            f"matplotlib writes no {out.suffix} (it writes .{', .'.join(writes)})"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    legend = {"Legend": json.dumps(figure_legend(fig))} if out.suffix.lower() == ".png" else None
    fig.savefig(out, metadata=legend)
    return out
