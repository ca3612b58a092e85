"""The table of docs/results/remedies/remedies.md from the runs' folder:
`.venv/bin/python docs/results/remedies/summary.py runs/remedies/out`.

Per run: the episode its success rate (a trailing mean of 3 evaluation points, 150
episodes) first reached 0.9, its peak, its mean over the last 10 points, the fall from
peak to that mean, the beta in force at its last point and, for a run its early_stop rule
ended, where. Per arm: the seeds' values and their mean."""

from __future__ import annotations

import sys

import pandas as pd

import macb

SMOOTH, LAST = 3, 10


def per_run(g: pd.DataFrame) -> dict[str, object]:
    g = g.sort_values("episode")
    s = g["success_rate"].rolling(SMOOTH, min_periods=SMOOTH).mean()
    hit = g["episode"][s >= 0.9]
    stop = g["stop_reason"].dropna()
    stop = stop[stop != ""]
    return {
        "episodes run": int(g["episode"].max()),
        "first >= 0.9": int(hit.iloc[0]) if len(hit) else None,
        "peak": round(float(s.max()), 3),
        "last 10 points": round(float(g["success_rate"].tail(LAST).mean()), 3),
        "fall": round(float(s.max() - g["success_rate"].tail(LAST).mean()), 3),
        "beta at the end": round(float(g["beta"].iloc[-1]), 3) if "beta" in g else None,
        "stopped by its rule at": int(g["episode"].max()) if len(stop) else None,
    }


def markdown(table: pd.DataFrame) -> str:
    """A pipe table (pandas' to_markdown needs tabulate, which the project does not pin)."""
    cells = [[("" if pd.isna(v) else f"{v:g}" if isinstance(v, float) else str(v)) for v in r]
             for r in table.itertuples(index=False)]  # fmt: skip
    lines = ["| " + " | ".join(map(str, table.columns)) + " |", "|" + "---|" * len(table.columns)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in cells])


def main(path: str) -> None:
    frame = macb.load_runs(path)
    rows = [{"arm": arm, "seed": int(seed), **per_run(g)} for (arm, seed), g in
            frame.groupby(["arm", "seed"], sort=False)]  # fmt: skip
    table = pd.DataFrame(rows)
    print(markdown(table))
    numeric = table.drop(columns="seed").groupby("arm", sort=False).mean(numeric_only=True)
    print()
    print(markdown(numeric.round(3).reset_index()))


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "runs/remedies/out")
