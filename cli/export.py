"""`macb export RUN_OR_EXPERIMENT`: a cluster run's (or a whole experiment's) stored
points as TensorBoard event files and/or CSV files.

The points come from the API (`--api`) or straight from a store file (`--db`, no API
needed). TensorBoard gets one folder per run, named by experiment, arm and seed
(`DIR/<experiment name>-<experiment id>/<arm>-seed<seed>/`, `-<run id>` added where two
arms' names give one folder name), so `tensorboard --logdir DIR` lists every run of every
exported experiment by those names; exporting again replaces a run's events rather than
doubling them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from cli.api import API_HELP, _api_client, _api_failed
from cli.store_file import NotAStore, store_copy


def add_export_parser(sub: argparse._SubParsersAction) -> None:
    ex = sub.add_parser(
        "export",
        help="write a run's or an experiment's metrics as TensorBoard events or CSV",
        description="Write every stored metric point of a run, or of every run of an "
        "experiment, as TensorBoard scalars (one folder per run, named by experiment, arm "
        "and seed; step = episode) and/or as CSV files (metrics.csv, metrics.jsonl, "
        "config.json and provenance.json per run, the experiment's metrics.csv).",
    )
    ex.add_argument("id", metavar="RUN_OR_EXPERIMENT", help="a run id or an experiment id")
    ex.add_argument("--tensorboard", metavar="DIR", help="write TensorBoard event files here")
    ex.add_argument("--csv", metavar="DIR", help="write CSV files here")
    ex.add_argument("--api", metavar="URL", help=API_HELP)
    ex.add_argument("--db", metavar="FILE", help="read this store instead of asking the API")
    ex.set_defaults(func=cmd_export)


def tensorboard_folders(
    root: Path, experiment: dict[str, Any], runs: list[dict[str, Any]]
) -> list[Path]:
    """DIR/<experiment name>-<id>/<arm>-seed<seed>: each of `runs`' folder, readable in
    TensorBoard's run list. Arms whose names differ only in characters a folder name
    cannot hold ("no bonus", "no_bonus") would share one, the second run's events
    deleting the first's: those runs' folders end in their run id too, whether the
    experiment or one run is exported (`experiment["runs"]`, all of them, decides)."""
    from collections import Counter

    from cli.tensorboard import run_folder_name

    def name(r: dict[str, Any]) -> str:
        return run_folder_name(r["arm"] or "run", f"seed{r['seed']}")

    every = Counter(name(r) for r in experiment.get("runs") or runs)
    parent = root / run_folder_name(experiment["name"], experiment["id"])
    return [
        parent / (run_folder_name(name(r), str(r["id"])) if every[name(r)] > 1 else name(r))
        for r in runs
    ]


def _from_store(db: str, ident: str) -> tuple[dict[str, Any], list[dict[str, Any]]] | None:
    """(experiment, its runs each with `points`) from a store file (`store_copy`); one
    run if `ident` is a run id."""
    with store_copy(db) as store:
        return _read_store(store, ident)


def _read_store(store: Any, ident: str) -> tuple[dict[str, Any], list[dict[str, Any]]] | None:
    """`_from_store` over an open store."""
    exp = store.experiment(ident)
    only = None
    if exp is None:
        run = store.run(ident)
        if run is None:
            return None
        exp, only = store.experiment(run["experiment_id"]), ident
        if exp is None:  # (a run's experiment is never deleted)
            return None
    every = store.runs_of([exp["id"]])[exp["id"]]
    runs = [dict(r, points=store.points(r["id"])) for r in every if only in (None, r["id"])]
    return {**exp, "runs": every}, runs


def _from_api(api: Any, ident: str) -> tuple[dict[str, Any], list[dict[str, Any]]] | None:
    from services.api.client import ApiError

    only = None
    try:
        exp = api.experiment(ident)
    except ApiError as err:
        if err.status != 404:
            raise
        try:
            run = api.run(ident)
        except ApiError as err2:
            if err2.status == 404:
                return None
            raise
        exp, only = api.experiment(run["experiment_id"]), ident
    runs = [dict(r, points=api.all_points(r["id"])) for r in exp["runs"] if only in (None, r["id"])]
    return exp, runs


def write_tensorboard(root: Path, exp: dict[str, Any], runs: list[dict[str, Any]]) -> list[Path]:
    from cli.tensorboard import TensorBoardRun

    folders = tensorboard_folders(root, exp, runs)
    for run, folder in zip(runs, folders, strict=True):
        with TensorBoardRun(folder, fresh=True) as tb:
            tb.write_all(run["points"])
    return folders


def write_csv(root: Path, exp: dict[str, Any], runs: list[dict[str, Any]]) -> None:
    """Per run (in root/ for one run, root/<run id>/ for several) metrics.csv with the
    store's columns, metrics.jsonl, config.json and provenance.json (what its learner ran
    on, where it reported it); the experiment's metrics.csv."""
    import csv

    from services.api.store import CSV_FIELDS
    from shared.persist import provenance

    def table(path: Path, rows: list[dict[str, Any]], first: list[str]) -> None:
        seen = {k for r in rows for k in r}
        extra = sorted(seen - set(CSV_FIELDS) - set(first) - {"seq"})
        with path.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=[*first, *CSV_FIELDS, *extra], extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)

    root.mkdir(parents=True, exist_ok=True)
    for run in runs:
        d = root if len(runs) == 1 else root / run["id"]
        d.mkdir(parents=True, exist_ok=True)
        table(d / "metrics.csv", run["points"], [])
        with (d / "metrics.jsonl").open("w") as f:
            for p in run["points"]:
                f.write(json.dumps({k: v for k, v in p.items() if k != "seq"}) + "\n")
        (d / "config.json").write_text(json.dumps(run["config"], indent=2) + "\n")
        if start := provenance.reported(run):
            provenance.write(d / provenance.FILE, [start])
    if len(runs) > 1:
        rows = [
            {**p, "arm": r["arm"], "seed": r["seed"], "run": r["id"]}
            for r in runs
            for p in r["points"]
        ]
        table(root / "metrics.csv", rows, ["arm", "seed", "run"])


def cmd_export(args: argparse.Namespace) -> int:
    import httpx

    from services.api.client import ApiError

    if not args.tensorboard and not args.csv:
        print("macb export: say where: --tensorboard DIR and/or --csv DIR", file=sys.stderr)
        return 2
    from cli.runs_folder import unwritable

    for flag, folder in (("--tensorboard", args.tensorboard), ("--csv", args.csv)):
        if folder and (why := unwritable(Path(folder))):
            print(f"macb export: {flag} {folder}: cannot write there ({why})", file=sys.stderr)
            return 2
    if args.db:
        from cli.store_file import store_file_error

        if why := store_file_error(args.db):
            print(f"macb export: {why}", file=sys.stderr)
            return 2
        try:
            found = _from_store(args.db, args.id)
        except NotAStore as err:
            print(f"macb export: {err}", file=sys.stderr)
            return 2
    else:
        try:
            with _api_client(args) as api:
                found = _from_api(api, args.id)
        except (ApiError, httpx.HTTPError) as err:
            return _api_failed("export", err)
    if found is None:
        where = args.db or "the API"
        print(f"macb export: no run or experiment {args.id!r} in {where}", file=sys.stderr)
        return 1
    exp, runs = found
    points = sum(len(r["points"]) for r in runs)
    if args.tensorboard:
        folders = write_tensorboard(Path(args.tensorboard), exp, runs)
        print(f"TensorBoard: {len(folders)} run(s), {points} points under {folders[0].parent}/")
    if args.csv:
        write_csv(Path(args.csv), exp, runs)
        print(f"CSV: {len(runs)} run(s), {points} points in {args.csv}/")
    return 0
