"""Many runs in this process as run groups (shared/group_trainer.py), without the bus:
what `macb train --seeds`, `macb run --local` and `macb reproduce --local` share.

Each run writes to its own folder under OUT (metrics.csv/jsonl, config.json,
provenance.json, checkpoint.pt, cuts/), exactly what `macb train --out` writes for it
alone. Runs are grouped by what they can share (`form_groups`); the same command run
again continues where it stopped: a group whose runs are all complete is skipped, one
whose runs all have cuts resumes from them, any other starts afresh.
"""

from __future__ import annotations

import json
import logging
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shared.config import TrainConfig

log = logging.getLogger("macb.local")


@dataclass
class LocalRun:
    """One run of a local experiment: its folder name (its id), arm and config."""

    name: str
    arm: str | None
    seed: int
    config: TrainConfig


def folder_name(text: str) -> str:
    """A run's name as a folder name (letters, digits, '.', '_', '-')."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or "run"


def _rows(folder: Path) -> list[dict[str, Any]]:
    path = folder / "metrics.jsonl"
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _same_config(folder: Path, cfg: TrainConfig) -> bool:
    try:
        written = json.loads((folder / "config.json").read_text())
    except (OSError, ValueError):
        return False
    return written == cfg.model_dump(mode="json")


def run_state(folder: Path, cfg: TrainConfig) -> str:
    """'done' (every episode run, checkpoint written), 'cut-<episode>' (can resume from
    its newest cut, of that episode) or 'new'."""
    if not _same_config(folder, cfg):
        return "new"
    rows = _rows(folder)
    if rows and rows[-1].get("episode") == cfg.episodes and (folder / "checkpoint.pt").exists():
        return "done"
    cuts = sorted((folder / "cuts").glob("cut-*.pt"))
    if cuts:
        return f"cut-{int(cuts[-1].stem.split('-')[1])}"
    return "new"


def run_groups(
    runs: list[LocalRun],
    out: Path,
    max_runs: int | None = None,
    quiet: bool = False,
    cut_every_s: float = 60.0,
) -> int:
    """Train `runs` as groups under `out`, continuing what an earlier call left; 0 when
    every run completed, 2 when a group could not resume (the reason printed).

    Complete runs are skipped one by one; the others are grouped by what they share and
    by where they stopped (runs that stopped together, at one cut, resume together;
    runs never started start together), so adding arms to a figure later neither
    restarts nor holds back the runs already under way."""
    from shared.cuts import CutError
    from shared.group_trainer import form_groups, train_group

    states = [run_state(out / r.name, r.config) for r in runs]
    todo = [i for i, s in enumerate(states) if s != "done"]
    if len(todo) < len(runs):
        print(f"{len(runs) - len(todo)} of {len(runs)} runs complete, skipped", file=sys.stderr)
    by_state: dict[str, list[int]] = {}
    for i in todo:
        by_state.setdefault(states[i], []).append(i)
    groups = []
    for state, idx in by_state.items():
        groups += [
            (state, [idx[j] for j in g])
            for g in form_groups([runs[i].config for i in idx], max_runs)
        ]
    for g, (state, members) in enumerate(groups, 1):
        chosen = [runs[i] for i in members]
        resume = state != "new"
        what = f"group {g}/{len(groups)} ({len(chosen)} runs: {chosen[0].config.task})"
        print(f"{what}: {'resuming from ' + state if resume else 'starting'}", file=sys.stderr)
        try:
            train_group(
                [r.config for r in chosen],
                [out / r.name for r in chosen],
                progress=not quiet,
                resume=resume,
                cut_every_s=cut_every_s,
            )
        except CutError as err:
            print(f"{what}: cannot resume: {err}", file=sys.stderr)
            return 2
    return 0


def local_experiment(name: str, seeds: list[int], runs: list[LocalRun], out: Path) -> dict:
    """The runs under `out` as the API would describe their experiment (what the
    report reads): each run's status, config and latest provenance."""
    from shared import provenance

    described = []
    for r in runs:
        folder = out / r.name
        state = run_state(folder, r.config)
        starts = []
        try:
            starts = provenance.read(folder / provenance.FILE)
        except provenance.ProvenanceError as err:
            log.warning("%s", err)
        described.append(
            {
                "id": r.name,
                "arm": r.arm or r.name,
                "seed": r.seed,
                "config": r.config.model_dump(mode="json"),
                "status": "completed" if state == "done" else "incomplete",
                "live": {"provenance": starts[-1] if starts else None},
            }
        )
    counts: dict[str, int] = {}
    for d in described:
        counts[d["status"]] = counts.get(d["status"], 0) + 1
    done = all(d["status"] == "completed" for d in described)
    return {
        "id": f"local:{out}",
        "name": name,
        "status": "completed" if done else "incomplete",
        "counts": counts,
        "seeds": seeds,
        "runs": described,
    }


def local_points(runs: list[LocalRun], out: Path) -> dict[str, list[dict[str, Any]]]:
    """Each run's metric rows, read from its folder."""
    return {r.name: _rows(out / r.name) for r in runs}


def expand_body(body: dict[str, Any]) -> tuple[str, list[int], list[LocalRun]]:
    """An experiment body (what POST /experiments takes) as the API expands it: its
    name, seeds and runs (arms outer, grid points, seeds inner), each named
    `<arm>-s<seed>` (the arm's name is its grid point's without arms)."""
    from services.api.schemas import ExperimentCreate

    exp = ExperimentCreate.model_validate(body)
    runs = []
    for e in exp.expand():
        arm = e["arm"]
        name = f"{folder_name(arm)}-s{e['seed']}"
        runs.append(LocalRun(name, arm, e["seed"], e["config"]))
    names = [r.name for r in runs]
    if len(set(names)) != len(names):
        raise ValueError("two runs would share a folder name; name the arms apart")
    return exp.name or exp.default_name(), exp.seed_list(), runs
