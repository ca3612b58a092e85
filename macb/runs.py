"""A runs folder as one pandas DataFrame: one row per evaluation point, so a notebook
reads what `macb train`, its `--seeds` groups and `macb reproduce --local` wrote without
parsing files by hand.

The columns: `run` (the run's folder name), `arm`, `seed`, then every field of the
metric rows as written (metrics.jsonl; metrics.csv when a folder has no jsonl), then the
run's config.json keys prefixed `config.` (nested ones joined with dots): a prefix, so a
config key never shadows a metric of the same name, and `frame.filter(like="config.")`
gives the config back.

A run being written may end in a torn line: that last line is skipped. Anything else
that does not read (a bad line before the last, a config.json that is not a JSON object,
no config.json) is refused with RunsError naming the file: a half-read frame would
silently change every mean taken from it.
"""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path
from typing import Any

import pandas as pd

CONFIG_PREFIX = "config."
METRIC_FILES = ("metrics.jsonl", "metrics.csv")
LEADING = ("run", "arm", "seed")


class RunsError(ValueError):
    """A runs folder that cannot be read as runs: the message names the path and why."""


def load_runs(path: str | Path) -> pd.DataFrame:
    """Every run under `path` as one frame (see the module's docstring for its columns).

    `path` is a run folder (it holds metrics.jsonl or metrics.csv), a folder of run
    folders (`macb train --seeds --out`, a reproduce's OUT/runs), or a reproduce's OUT
    (its runs/ is read, and its FIGURE-runs.json, when written, names each run's arm).
    Runs are in folder-name order, each run's rows in the order written."""
    root = Path(path)
    if not root.is_dir():
        raise RunsError(f"{root}: no such folder")
    folders, arms = _run_folders(root)
    if not folders:
        raise RunsError(
            f"{root}: no runs (no folder holding {' or '.join(METRIC_FILES)}, here or one "
            "level down, nor under runs/)"
        )
    return joined([_run_frame(f, arms.get(f.name)) for f in folders])


def load_page(path: str | Path) -> pd.DataFrame:
    """A figure page's points (`macb reproduce` writes FIGURE.csv.gz; older pages hold a
    plain FIGURE.csv): `path` is the page's folder (docs/results/fig8-thesis) or the
    file. One row per point: arm, seed, run, episode, env_steps, the metrics the report
    reads; a cell left empty (no value) is NaN. RunsError when there is none."""
    from cli.results import points_file

    page = Path(path)
    found: Path | None = page if page.is_file() else None
    if page.is_dir():
        for claims in sorted(page.glob("*-claims.json")):
            found = found or points_file(page, claims.name.removesuffix("-claims.json"))
    if found is None:
        raise RunsError(f"{page}: no page's points (FIGURE.csv.gz or FIGURE.csv) there")
    return pd.read_csv(found)  # gzip inferred from the name


def joined(frames: list[pd.DataFrame]) -> pd.DataFrame:
    """Runs' frames as one: run, arm, seed, the metrics, then the config keys sorted."""
    frame = pd.concat(frames, ignore_index=True, sort=False)
    config = sorted(c for c in frame.columns if c.startswith(CONFIG_PREFIX))
    metrics = [c for c in frame.columns if c not in LEADING and c not in config]
    return frame[[*LEADING, *metrics, *config]]


def is_run_folder(folder: Path) -> bool:
    """A run's folder: its metrics.jsonl, or its metrics.csv beside its config.json (a
    `macb run --out` folder of several runs has the experiment's metrics.csv and no
    config)."""
    if (folder / "metrics.jsonl").is_file():
        return True
    return (folder / "metrics.csv").is_file() and (folder / "config.json").is_file()


def _run_folders(root: Path) -> tuple[list[Path], dict[str, str]]:
    """The run folders under root, and the arm of each run a reproduce record names."""
    if is_run_folder(root):
        return [root], {}
    base = root / "runs" if (root / "runs").is_dir() else root
    folders = sorted(p for p in base.iterdir() if p.is_dir() and is_run_folder(p))
    return folders, _recorded_arms(root)


def _recorded_arms(root: Path) -> dict[str, str]:
    """id -> arm from a reproduce's FIGURE-runs.json (cli/reproduce/page.py), or from the
    experiment's metrics.csv `macb run --out` writes beside its runs' folders."""
    arms: dict[str, str] = {}
    table = root / "metrics.csv"
    if table.is_file():
        with table.open(newline="") as f:
            for r in csv.DictReader(f):
                if r.get("run") and r.get("arm") is not None:
                    arms.setdefault(r["run"], r["arm"])
    for record in sorted(root.glob("*-runs.json")):
        try:
            runs = json.loads(record.read_text()).get("runs") or []
        except (OSError, ValueError, AttributeError) as err:
            raise RunsError(f"{record}: not a reproduce runs record ({err})") from err
        arms.update({str(r["id"]): str(r["arm"]) for r in runs if "id" in r and "arm" in r})
    return arms


def read_config(folder: Path) -> dict[str, Any]:
    path = folder / "config.json"
    if not path.is_file():
        raise RunsError(f"{path}: missing (every run folder holds its config)")
    try:
        config = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise RunsError(f"{path}: unreadable ({err})") from err
    if not isinstance(config, dict):
        raise RunsError(f"{path}: not a JSON object")
    return config


def read_rows(folder: Path) -> list[dict[str, Any]]:
    """The run's metric rows; a torn last line of metrics.jsonl is skipped."""
    path = folder / "metrics.jsonl"
    if not path.is_file():
        return _csv_rows(folder / "metrics.csv")
    lines = [x for x in path.read_text().splitlines() if x.strip()]
    rows = []
    for i, line in enumerate(lines, 1):
        try:
            row = json.loads(line)
        except ValueError as err:
            if i == len(lines):  # a row being written
                break
            raise RunsError(f"{path}: line {i} is not a JSON row ({err})") from err
        if not isinstance(row, dict):
            raise RunsError(f"{path}: line {i} is not a JSON object")
        rows.append(row)
    return rows


def _csv_rows(path: Path) -> list[dict[str, Any]]:
    with path.open(newline="") as f:
        lines = list(csv.reader(f))
    if not lines:
        return []
    head, body = lines[0], lines[1:]
    if body and len(body[-1]) != len(head):  # a row being written
        body = body[:-1]
    for i, cells in enumerate(body, 2):
        if len(cells) != len(head):
            raise RunsError(f"{path}: line {i} has {len(cells)} cells, the header {len(head)}")
    return [{k: _cell(v) for k, v in zip(head, cells, strict=True)} for cells in body]


def _cell(text: str) -> Any:
    if text == "":
        return math.nan
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


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
    flat = _flatten(config)
    extra = pd.DataFrame({k: [v] * len(frame) for k, v in flat.items()}, index=frame.index)
    return pd.concat([frame, extra], axis=1)


def arm_of(folder: Path, seed: Any) -> str:
    """A run's arm from its folder's name: `<arm>-s<seed>` (a reproduce's runs), `seed-<seed>`
    (`macb train --seeds`: the seeds of one config, named by their parent folder), else
    the folder's name (one `macb train` run)."""
    name = folder.name
    if m := re.fullmatch(rf"(.+)-s{seed}", name):
        return m.group(1)
    if name == f"seed-{seed}":
        return folder.resolve().parent.name
    return name


def _flatten(config: dict[str, Any], prefix: str = CONFIG_PREFIX) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in config.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = tuple(value) if isinstance(value, list) else value
    return out
