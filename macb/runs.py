"""A runs folder as one pandas DataFrame: one row per evaluation point, so a notebook
reads what `macb train`, its `--seeds` groups and `macb reproduce --local` wrote without
parsing files by hand.

The columns: `run` (the run's folder name), `arm`, `seed`, then every field of the
metric rows as written (metrics.jsonl; metrics.csv when a folder has no jsonl), then the
run's config.json keys prefixed `config.` (nested ones joined with dots): a prefix, so a
config key never shadows a metric of the same name, and `frame.filter(like="config.")`
gives the config back.

A run with no row yet (started, nothing evaluated) has no row in the frame, so
`macb.summary` counts the runs with a point; the report (FIGURE.md) counts the figure's
runs and says "no points" for an arm while one of its runs has none.

A run being written may end in a torn line: that last line is skipped. Anything else
that does not read (a bad line before the last, a config.json that is not a JSON object,
no config.json) is refused with RunsError naming the file: a half-read frame would
silently change every mean taken from it.
"""

from __future__ import annotations

import zlib
from pathlib import Path
from typing import Any

import pandas as pd

from cli.runs_folder import (
    RunsError,
    arm_of,
    read_config,
    read_rows,
    runs_in,
)

CONFIG_PREFIX = "config."
LEADING = ("run", "arm", "seed")


def load_runs(path: str | Path) -> pd.DataFrame:
    """Every run under `path` as one frame (see the module's docstring for its columns).

    `path` is a run folder (it holds metrics.jsonl or metrics.csv), a folder of run
    folders (`macb train --seeds --out`, a reproduce's OUT/runs), or a reproduce's OUT
    (its runs/ is read, and its FIGURE-runs.json, when written, names each run's arm).
    Runs are in folder-name order, each run's rows in the order written."""
    folders, arms = runs_in(Path(path))
    return joined([_run_frame(f, arms.get(f.name)) for f in folders])


def load_page(path: str | Path) -> pd.DataFrame:
    """A figure page's points (`macb reproduce` writes FIGURE.csv.gz; older pages hold a
    plain FIGURE.csv): `path` is the page's folder (docs/results/fig8-thesis) or the
    file. One row per point: arm, seed, run, episode, env_steps, the metrics the report
    reads; a cell left empty (no value) is NaN. RunsError when there is none."""
    from cli.results import points_file, points_files

    page = Path(path)
    if not page.exists():
        raise RunsError(f"{page}: no such page (a folder holding FIGURE.csv.gz, or the file)")
    found: Path | None = page if page.is_file() else None
    if page.is_dir():
        for claims in sorted(page.glob("*-claims.json")):
            found = found or points_file(page, claims.name.removesuffix("-claims.json"))
        if found is None:  # a page's points copied without its claims file: the one there
            files = points_files(page)
            if len(files) > 1:
                names = ", ".join(f.name for f in files)
                raise RunsError(f"{page}: which page's points? it holds {names}: give the file")
            found = files[0] if files else None
    if found is None:
        raise RunsError(f"{page}: no page's points (FIGURE.csv.gz or FIGURE.csv) there")
    try:
        frame = pd.read_csv(found)  # gzip inferred from the name
    except (OSError, EOFError, ValueError, zlib.error) as err:  # torn or corrupt; not a CSV
        raise RunsError(f"{found}: not a page's points ({err})") from err
    if missing := [c for c in ("run", "episode") if c not in frame.columns]:
        raise RunsError(f"{found}: not a page's points (no {' or '.join(missing)} column)")
    return frame


def joined(frames: list[pd.DataFrame]) -> pd.DataFrame:
    """Runs' frames as one: run, arm, seed, the metrics, then the config keys sorted. A
    run without a row yet adds none: its empty frame, concatenated, would make every
    other run's integer columns float (pandas' common type with an empty object column)."""
    if any(len(f) for f in frames):
        frames = [f for f in frames if len(f)]
    frame = pd.concat(frames, ignore_index=True, sort=False)
    config = sorted(c for c in frame.columns if c.startswith(CONFIG_PREFIX))
    metrics = [c for c in frame.columns if c not in LEADING and c not in config]
    return frame[[*LEADING, *metrics, *config]]


def _run_frame(folder: Path, recorded_arm: str | None) -> pd.DataFrame:
    config = read_config(folder)
    seed = config.get("seed")
    arm = recorded_arm or arm_of(folder, seed)
    return run_frame(folder.name, arm, seed, read_rows(folder), config)


def run_frame(
    run: str, arm: str, seed: Any, rows: list[dict[str, Any]], config: dict[str, Any]
) -> pd.DataFrame:
    """One run's rows with its name, arm, seed and config as columns."""
    frame = pd.DataFrame.from_records(rows) if rows else pd.DataFrame({"episode": []})
    frame.insert(0, "run", run)
    frame.insert(1, "arm", arm)
    frame.insert(2, "seed", seed)
    flat = flatten_config(config)
    extra = pd.DataFrame({k: [v] * len(frame) for k, v in flat.items()}, index=frame.index)
    return pd.concat([frame, extra], axis=1)


def flatten_config(config: dict[str, Any], prefix: str = CONFIG_PREFIX) -> dict[str, Any]:
    """A config as the frame's columns: `config.`-prefixed keys, nested ones joined with
    dots, lists as tuples (a cell holds one value)."""
    out: dict[str, Any] = {}
    for key, value in config.items():
        if isinstance(value, dict):
            out.update(flatten_config(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = tuple(value) if isinstance(value, list) else value
    return out


__all__ = [
    "CONFIG_PREFIX",
    "RunsError",
    "arm_of",
    "flatten_config",
    "joined",
    "load_runs",
    "read_config",
    "read_rows",
    "run_frame",
]
