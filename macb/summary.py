"""A figure's summary from a runs frame: what the report (FIGURE.md) says about the same
runs, as DataFrames, by calling the report's own functions (cli/reproduce/analysis.py,
controls.py, render.py). This module only adapts a frame to the structures they take
(an experiment description and each run's columns); it computes nothing itself, so the
notebook and the page cannot disagree.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import pandas as pd

from cli.local import folder_name
from cli.reproduce.analysis import (
    LOADED,
    Analysis,
    Columns,
    analyse,
    claim_verdicts,
    columns,
)
from cli.reproduce.controls import control_verdicts, why_rows
from cli.reproduce.defs import FigureDef
from cli.reproduce.experiments import arm_configs
from cli.reproduce.figures import FIGURES
from cli.reproduce.render import measured
from macb.runs import CONFIG_PREFIX, RunsError, flatten_config


@dataclass
class FigureSummary:
    """A figure's summary, each part a frame of the report's values and words."""

    figure: str
    arms: pd.DataFrame  # per arm: runs, episodes reached, window, plateau, convergence
    claims: pd.DataFrame  # per claim: the thesis's words, measured, verdict
    controls: pd.DataFrame  # per counting arm: its control and the verdict
    why: pd.DataFrame  # per counting arm: end, count-1 %, bonus paid, against its control
    curves: pd.DataFrame  # per arm and episode: the smoothed mean and the band drawn
    analysis: Analysis  # the report's own object, for anything not tabulated here


def summary(frame: pd.DataFrame, figure: str | FigureDef) -> FigureSummary:
    """The summary of `figure` (a name in `macb reproduce`'s figures, or its definition)
    over the runs of `frame` (from load_runs). A run's arm is matched to the figure's by
    name or by its folder name (`Sparse + Dis-MACB` is `Sparse_Dis-MACB`); runs of other
    arms are left out. RunsError when no run belongs to the figure, or when a run named
    as one of its arms was run with another value of a key that arm's config file sets
    (`arm_mismatch`)."""
    fig = _figure(figure)
    exp, points = experiment(frame, fig)
    a = analyse(fig, exp, points)
    return FigureSummary(
        figure=fig.name,
        arms=_arms(a),
        claims=pd.DataFrame(
            [
                {"claim": c.text, "where": c.where, "thesis": c.thesis, "measured": m, "verdict": v}
                for c, m, v in claim_verdicts(a)
            ],
            columns=["claim", "where", "thesis", "measured", "verdict"],
        ),
        controls=pd.DataFrame(
            control_verdicts(a),
            columns=["arm", "control", "arm_measured", "control_measured", "verdict"],
        ),
        why=pd.DataFrame(
            [[*r[:5], r[5].strip("*")] for r in why_rows(a)],
            columns=["arm", "at_the_end", "count1_pct", "bonus_paid", "control", "verdict"],
        ),
        curves=_curves(a),
        analysis=a,
    )


def _figure(figure: str | FigureDef) -> FigureDef:
    if isinstance(figure, FigureDef):
        return figure
    if figure not in FIGURES:
        raise ValueError(f"no figure {figure!r}; the figures: {', '.join(FIGURES)}")
    return FIGURES[figure]


def experiment(frame: pd.DataFrame, fig: FigureDef) -> tuple[dict[str, Any], dict[str, Columns]]:
    """The frame's runs of `fig` as the report takes them: the experiment (as GET
    /experiments/{id} describes it) and each run's columns (analysis.columns)."""
    names = {a.name: a.name for a in fig.arms} | {folder_name(a.name): a.name for a in fig.arms}
    configs = arm_configs(fig)
    runs: list[dict[str, Any]] = []
    points: dict[str, Columns] = {}
    fields = [f for f in ("episode", *LOADED, "stop_reason") if f in frame.columns]
    for run, rows in frame.groupby("run", sort=True):
        arm = names.get(str(rows["arm"].iloc[0]))
        if arm is None:
            continue
        if why := arm_mismatch(rows.iloc[0], configs[arm], fig):
            raise RunsError(f"run {run} is not {fig.name}'s arm {arm!r}: {why}")
        runs.append({"id": str(run), "arm": arm, "seed": int(rows["seed"].iloc[0])})
        kept = rows.loc[rows["episode"].notna(), fields]
        points[str(run)] = columns(kept.to_dict("records"))
    if not runs:
        arms = ", ".join(sorted(map(str, frame["arm"].unique()))) or "none"
        raise RunsError(f"no run of the frame is an arm of {fig.name} (the frame's arms: {arms})")
    exp = {
        "id": "frame",
        "name": fig.name,
        "seeds": sorted({r["seed"] for r in runs}),
        "runs": runs,
    }
    return exp, points


def arm_mismatch(row: pd.Series, arm_config: dict[str, Any], fig: FigureDef) -> str | None:
    """Why a run's `config.*` cells (`row`) are not of an arm: the first key its config
    file sets to another value ('key: x in the run, y in the arm'), or None. Not compared:
    what `macb reproduce` flags change (episodes, seeds) and the keys a profile sets over
    the file (the figure's `thesis_method`); a key the frame lacks (a config from before
    it existed) says nothing."""
    skip = {"episodes", "seeds", "seed"} | {k for k, _ in fig.thesis_method}
    for column, want in flatten_config(arm_config).items():  # as load_runs names them
        key = column.removeprefix(CONFIG_PREFIX)
        if key.split(".")[0] in skip or column not in row.index:
            continue
        have = row[column]
        have = have.item() if hasattr(have, "item") else have  # numpy scalar: Python's
        if isinstance(have, float) and have != have:
            continue  # NaN: this run's config has no such key (other runs' configs do)
        if not bool(have == want):
            return f"{key}: {have!r} in the run, {want!r} in the arm"
    return None


def _arms(a: Analysis) -> pd.DataFrame:
    configs = arm_configs(a.fig)
    rows = []
    for arm_def in a.fig.arms:
        arm = a.arm(arm_def.name)
        has = len(arm.episodes) > 0
        rows.append(
            {
                "arm": arm_def.name,
                "runs": len(arm.runs),
                "seeds": tuple(arm.seeds),
                "episodes": arm.length,
                "window": arm.window,
                "plateau": arm.plateau,
                "converged": arm.converged if has else None,
                "final": arm.final if has else None,
                "measured": measured(a, arm_def.name, configs[arm_def.name]),
                "thesis": arm_def.thesis,
            }
        )
    return pd.DataFrame(rows).set_index("arm")


def _curves(a: Analysis) -> pd.DataFrame:
    parts = []
    for name, arm in a.arms.items():
        if not len(arm.episodes):
            continue
        low, high = arm.band()
        parts.append(
            pd.DataFrame(
                {
                    "arm": name,
                    "episode": arm.episodes,
                    "mean": arm.curve(),
                    "low": low,
                    "high": high,
                }
            )
        )
    if not parts:
        return pd.DataFrame(columns=["arm", "episode", "mean", "low", "high"])
    return pd.concat(parts, ignore_index=True)
