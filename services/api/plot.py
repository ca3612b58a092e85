"""The thesis-style figure: a metric against training episodes, per arm the mean over
seeds with a band (mean +- one standard deviation), from stored metrics."""

from __future__ import annotations

from pathlib import Path
from typing import Any

LABELS = {
    "success_rate": "success rate",
    "count1_pct": "count-1 % (keys seen once)",
    "steps_per_sec": "env steps / s",
    "eval_return": "evaluation return",
    "collisions_cum": "cumulative collisions",
}


def plot_curves(curves: dict[str, Any], metric: str, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = curves["metrics"].get(metric, [])
    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    for g in groups:
        if not g["episode"]:
            continue
        seeds = len(g["runs"])
        (line,) = ax.plot(g["episode"], g["mean"], lw=1.6, label=f"{g['label']} ({seeds} seeds)")
        ax.fill_between(g["episode"], g["lo"], g["hi"], color=line.get_color(), alpha=0.2, lw=0)
    ax.set_xlabel("training episodes")
    ax.set_ylabel(LABELS.get(metric, metric))
    if metric == "success_rate":
        ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    subtitle = "(mean over seeds, band: ± one standard deviation)"
    ax.set_title(f"{curves['name']}\n{subtitle}", fontsize=10)
    if any(g["episode"] for g in groups):
        ax.legend(fontsize=8, loc="best")
    else:
        ax.text(0.5, 0.5, "no metric points stored yet", ha="center", transform=ax.transAxes)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out
