"""A runs folder's runs as written: which folders are runs, each one's config, arm,
seed and metric rows (metrics.jsonl, else metrics.csv). One reader for the Python API
(macb/runs.py, its DataFrame) and the figure view of a folder (cli/view.py), so both see
the same runs, arms and rows.

A run being written may end in a torn line: that last line is skipped. Anything else
that does not read is refused with RunsError naming the file: a half-read run would
silently change every mean taken from it.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import re
import tempfile
from pathlib import Path
from typing import Any

METRIC_FILES = ("metrics.jsonl", "metrics.csv")


class RunsError(ValueError):
    """A runs folder that cannot be read as runs: the message names the path and why."""


def runs_in(root: Path) -> tuple[list[Path], dict[str, str]]:
    """The run folders under `root` (see run_folders) and each recorded arm; RunsError
    when `root` is no folder or holds no run."""
    if not root.is_dir():
        raise RunsError(f"{root}: {'a file, not a folder' if root.exists() else 'no such folder'}")
    folders, arms = run_folders(root)
    if not folders:
        raise RunsError(
            f"{root}: no runs (no folder holding {' or '.join(METRIC_FILES)}, here or one "
            "level down, nor under runs/)"
        )
    return folders, arms


def is_run_folder(folder: Path) -> bool:
    """A run's folder: its metrics.jsonl, or its metrics.csv beside its config.json (a
    `macb run --out` folder of several runs has the experiment's metrics.csv and no
    config)."""
    if (folder / "metrics.jsonl").is_file():
        return True
    return (folder / "metrics.csv").is_file() and (folder / "config.json").is_file()


def run_folders(root: Path) -> tuple[list[Path], dict[str, str]]:
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
        try:
            with table.open(newline="") as f:
                for r in csv.DictReader(f):
                    if r.get("run") and r.get("arm") is not None:
                        arms.setdefault(r["run"], r["arm"])
        except (OSError, UnicodeDecodeError, csv.Error) as err:
            raise RunsError(f"{table}: unreadable ({err})") from err
    for record in sorted(root.glob("*-runs.json")):
        try:
            runs = json.loads(record.read_text()).get("runs") or []
        except (OSError, ValueError, AttributeError) as err:
            raise RunsError(f"{record}: not a reproduce runs record ({err})") from err
        if not isinstance(runs, list) or not all(isinstance(r, dict) for r in runs):
            raise RunsError(f"{record}: not a reproduce runs record (runs: not a list of objects)")
        arms.update({str(r["id"]): str(r["arm"]) for r in runs if "id" in r and "arm" in r})
    return arms


def unwritable(folder: Path, make: bool = False) -> str | None:
    """Why a file cannot be created in `folder`, or None: asked before a command writes
    there, so that it refuses instead of failing midway. A missing folder is made with
    `make`; without it nothing is left behind (a command that fails later, its source
    unreadable, leaves no empty folder): the nearest folder that exists is probed."""
    if folder.exists() and not folder.is_dir():
        return "a file, not a folder"
    if folder.is_symlink() and not folder.exists():
        return "a symbolic link to nothing"
    probe = folder
    try:
        if make:
            folder.mkdir(parents=True, exist_ok=True)
        while not os.path.lexists(probe) and probe != probe.parent:
            probe = probe.parent
        if not probe.is_dir():
            return f"{probe} is a file, not a folder"
        with tempfile.NamedTemporaryFile(dir=probe, prefix=".macb-write-check-"):
            pass
    except OSError as err:
        return err.strerror or str(err)
    return None


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


class RowError(ValueError):
    """A line of a metrics.jsonl, not its last, that is not a JSON row."""

    def __init__(self, line: int, why: str) -> None:
        super().__init__(f"line {line}: not a metric row ({why})")
        self.line = line


def jsonl_rows(path: Path) -> list[dict[str, Any]]:
    """A metrics.jsonl's rows as written so far, the one reading of every reader. A last
    line without its newline is a row being written by a run still going, not yet a
    row; a last line that does not read (JSON in UTF-8) is one a killed process left
    torn: both are left out (a resume writes the rows again from its cut). Another line
    that does not read (NUL bytes where two processes wrote at once) raises RowError
    naming it. OSError when the file cannot be read."""
    data = path.read_bytes()
    lines = data[: data.rfind(b"\n") + 1].split(b"\n")[:-1]  # each ended by its newline
    rows = []
    for i, raw in enumerate(lines, 1):
        if not raw.strip():
            continue
        try:
            row = json.loads(raw.decode())
            if not isinstance(row, dict):
                raise ValueError(f"a {type(row).__name__}, not an object")
        except ValueError as err:  # (UnicodeDecodeError too)
            if i == len(lines):
                break
            raise RowError(i, str(err)[:80]) from None
        rows.append(row)
    return rows


def read_rows(folder: Path) -> list[dict[str, Any]]:
    """The run's metric rows (`jsonl_rows`; a folder with only a metrics.csv, its rows). A
    row whose episode is not a whole number is refused (every reader indexes points by
    it)."""
    path = folder / "metrics.jsonl"
    if not path.is_file():
        return _checked(folder / "metrics.csv", _csv_rows(folder / "metrics.csv"))
    try:
        rows = jsonl_rows(path)
    except OSError as err:
        raise RunsError(f"{path}: unreadable ({err})") from err
    except RowError as err:
        raise RunsError(f"{path}: {err}") from None
    return _checked(path, rows)


def _checked(path: Path, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """`rows`, each episode (where given) an int; else RunsError naming the row."""
    for n, row in enumerate(rows, 1):
        episode = row.get("episode", 0)
        if not isinstance(episode, int) or isinstance(episode, bool):
            raise RunsError(f"{path}: row {n} has episode {episode!r}, not a whole number")
    return rows


def _csv_rows(path: Path) -> list[dict[str, Any]]:
    """metrics.csv's rows; a last line without its newline is a row being written (a
    tear inside its last cell keeps the cell count) and is skipped."""
    try:
        text = path.read_text()
        lines = list(csv.reader(io.StringIO(text)))
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise RunsError(f"{path}: unreadable ({err})") from err
    if not lines:
        return []
    head, body = lines[0], lines[1:]
    if body and (not text.endswith("\n") or len(body[-1]) != len(head)):  # being written
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
