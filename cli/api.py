"""The commands that go through the HTTP API: `run`, `ls`, `stop` and `plot`.

They are clients of services.api (`macb up` or `macb serve api` must be running), except
`plot --db`, which reads a store file, and `stop --bus`, which `cli.cluster` sends.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from cli.config_flags import add_config_flags, config_overrides
from shared.config import ConfigError, TrainConfig, make_config, read_config_file

if TYPE_CHECKING:
    from services.api.client import ApiClient

API_HELP = "API base URL (default: MACB_API_URL or http://127.0.0.1:8000)"


# ---------------------------------------------------------------- parsers
def add_stop_parser(sub: argparse._SubParsersAction) -> None:
    sp = sub.add_parser(
        "stop",
        help="stop a run or an experiment (through the API)",
        description="Stop a run or every run of an experiment through the API. With --bus, "
        "send the stop for a run id straight on the bus (runs started with macb start).",
    )
    sp.add_argument("id", help="run id or experiment id")
    sp.add_argument("--api", metavar="URL", help=API_HELP)
    sp.add_argument("--bus", action="store_true", help="send the stop on the bus, not the API")
    sp.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint")
    sp.set_defaults(func=cmd_stop)


def add_run_parser(sub: argparse._SubParsersAction) -> None:
    rn = sub.add_parser(
        "run",
        help="submit an experiment to the API and follow it to the end",
        description="Submit CONFIG (a YAML/JSON config, keys overridden by flags) as an "
        "experiment: one run per seed and grid point, queued until services are free. "
        "Shows a progress bar until every run has ended; Ctrl-C stops the experiment.",
    )
    rn.add_argument("config", metavar="CONFIG", help="YAML/JSON config file")
    rn.add_argument("--seeds", type=int, nargs="+", metavar="SEED", help="one run per seed")
    rn.add_argument(
        "--grid",
        action="append",
        metavar="KEY=V1,V2",
        help="sweep beta or k (repeat for both): --grid beta=0.2,0.8 --grid k=64,512",
    )
    rn.add_argument("--name", help="experiment name")
    rn.add_argument("--actors", type=int, default=1, help="actors per run")
    rn.add_argument("--api", metavar="URL", help=API_HELP)
    rn.add_argument("--out", metavar="DIR", help="write metrics.csv and plot.png here")
    rn.add_argument("--detach", action="store_true", help="submit, print the id and return")
    rn.add_argument("--quiet", action="store_true", help="no progress bar")
    add_config_flags(rn)
    rn.set_defaults(func=cmd_run)


def add_ls_parser(sub: argparse._SubParsersAction) -> None:
    ls = sub.add_parser("ls", help="list experiments and their runs (through the API)")
    ls.add_argument("--api", metavar="URL", help=API_HELP)
    ls.add_argument("--limit", type=int, default=20, help="newest N experiments")
    ls.set_defaults(func=cmd_ls)


def add_plot_parser(sub: argparse._SubParsersAction) -> None:
    pl = sub.add_parser(
        "plot",
        help="draw an experiment's learning curves (mean over seeds with a band) to a PNG",
    )
    pl.add_argument("experiment", metavar="EXPERIMENT_ID")
    pl.add_argument("-o", "--output", required=True, metavar="FILE.png")
    pl.add_argument("--metric", default="success_rate", help="metric to plot")
    pl.add_argument("--api", metavar="URL", help=API_HELP)
    pl.add_argument("--db", metavar="FILE", help="read this store instead of asking the API")
    pl.set_defaults(func=cmd_plot)


# ---------------------------------------------------------------- helpers
def _api_client(args: argparse.Namespace) -> ApiClient:
    from services.api.client import ApiClient

    return ApiClient(getattr(args, "api", None))


def _api_failed(cmd: str, err: Exception | str) -> int:
    print(f"macb {cmd}: {err}", file=sys.stderr)
    return 1


def _read_config_file(path: str) -> dict[str, Any]:
    """The file's mapping as written: the body sends every key on (a file may also hold
    the experiment's `seeds`, `grid` or `name`), and the API judges what is not config."""
    return read_config_file(path)


def _grid(items: list[str] | None) -> dict[str, list]:
    """`--grid beta=0.2,0.8 --grid k=64,512` as {"beta": [0.2, 0.8], "k": [64, 512]}."""
    grid: dict[str, list] = {}
    for item in items or []:
        key, _, values = item.partition("=")
        if key not in ("beta", "k") or not values:
            raise ConfigError(f"--grid {item}: use beta=V1,V2,... or k=V1,V2,...")
        grid[key] = [yaml.safe_load(v) for v in values.split(",") if v.strip()]
    return grid


def experiment_body(args: argparse.Namespace) -> dict[str, Any]:
    """The POST /experiments body from a config file, flags, --seeds and --grid."""
    body: dict[str, Any] = {}
    if getattr(args, "config", None):
        body.update(_read_config_file(args.config))
    body.update(config_overrides(args))
    make_config({k: v for k, v in body.items() if k in TrainConfig.model_fields})
    if args.seeds:
        body.pop("seed", None)
        body["seeds"] = args.seeds
    grid = _grid(args.grid)
    if grid:
        body["grid"] = grid
    if args.name:
        body["name"] = args.name
    body["actors"] = args.actors
    return body


def write_results(
    api: ApiClient, exp: dict[str, Any], out: Path, plot: bool = True, data_dir: Path | None = None
) -> list[Path]:
    """Each run's metrics.csv, metrics.jsonl, config.json (and, with the cluster's data
    dir, the learner's checkpoint.pt) in out/ for one run or out/<run id>/ for several;
    out/plot.png."""
    import json
    import shutil

    out.mkdir(parents=True, exist_ok=True)
    written = []
    for run in exp["runs"]:
        d = out if len(exp["runs"]) == 1 else out / run["id"]
        d.mkdir(parents=True, exist_ok=True)
        (d / "metrics.csv").write_text(api.metrics_csv(run["id"]))
        points = api.metrics(run["id"])["points"]
        with (d / "metrics.jsonl").open("w") as f:
            for p in points:
                f.write(json.dumps({k: v for k, v in p.items() if k != "seq"}) + "\n")
        (d / "config.json").write_text(json.dumps(run["config"], indent=2) + "\n")
        written.append(d / "metrics.csv")
        checkpoint = data_dir / "learner" / run["id"] / "checkpoint.pt" if data_dir else None
        if checkpoint is not None and checkpoint.exists():
            shutil.copyfile(checkpoint, d / "checkpoint.pt")
    if plot:
        from services.api.plot import plot_curves

        written.append(
            plot_curves(api.curves(exp["id"], ["success_rate"]), "success_rate", out / "plot.png")
        )
    return written


def _print_runs(exp: dict[str, Any]) -> None:
    for run in exp["runs"]:
        last = run["live"].get("eval") or {}
        print(
            f"run {run['id']} {run['status']}: {run['points']} evaluation points, final success "
            f"{last.get('success_rate', 0):.2f}, {last.get('steps_per_sec', 0):.1f} env steps/s"
            + (f" ({run['reason']})" if run["reason"] else ""),
            file=sys.stderr,
        )


def run_via_api(
    api: ApiClient,
    body: dict[str, Any],
    out: Path | None,
    quiet: bool,
    data_dir: Path | None = None,
) -> int:
    """Submit an experiment, follow it to the end, write its results; exit code."""
    from services.api.client import follow_experiment

    exp = api.create_experiment(body)
    print(
        f"experiment {exp['id']}: {len(exp['runs'])} run(s) queued; "
        f"follow it at {api.url}/  (macb stop {exp['id']} stops it)",
        file=sys.stderr,
    )
    try:
        exp = follow_experiment(api, exp["id"], quiet=quiet)
    except KeyboardInterrupt:
        api.stop_experiment(exp["id"])
        exp = api.experiment(exp["id"])
        print(f"experiment {exp['id']} stopped", file=sys.stderr)
    _print_runs(exp)
    if out is not None:
        write_results(api, exp, out, data_dir=data_dir)
        print(f"results in {out}/ (metrics.csv, plot.png)", file=sys.stderr)
    print(f"experiment {exp['id']} {exp['status']}", file=sys.stderr)
    return 0 if exp["status"] == "completed" else 1


# ---------------------------------------------------------------- commands
def cmd_stop(args: argparse.Namespace) -> int:
    if not args.bus:
        return _api_stop(args)
    # Imported here: cli.cluster imports this module (`up` runs experiments through it).
    from cli.cluster import stop_on_bus

    return stop_on_bus(args)


def _api_stop(args: argparse.Namespace) -> int:
    """A run id or an experiment id, through the API."""
    import httpx

    from services.api.client import ApiError

    try:
        with _api_client(args) as api:
            try:
                out = api.stop_run(args.id)
                print(f"run {args.id}: {out['detail']} (status {out['run']['status']})")
            except ApiError as err:
                if err.status != 404:
                    raise
                out = api.stop_experiment(args.id)
                print(f"experiment {args.id}: {out['detail']}")
    except ApiError as err:
        if err.status == 404:
            print(f"macb stop: no run or experiment {args.id!r}", file=sys.stderr)
            return 1
        return _api_failed("stop", err)
    except httpx.HTTPError as err:
        return _api_failed("stop", f"cannot reach the API: {err}")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    import httpx

    from services.api.client import ApiError

    try:
        body = experiment_body(args)
    except (ConfigError, OSError) as err:
        print(f"macb run: invalid config: {err}", file=sys.stderr)
        return 2
    try:
        with _api_client(args) as api:
            if args.detach:
                exp = api.create_experiment(body)
                print(exp["id"])
                return 0
            return run_via_api(api, body, Path(args.out) if args.out else None, args.quiet)
    except ApiError as err:
        if err.status == 422:
            print(f"macb run: invalid config: {err}", file=sys.stderr)
            return 2
        return _api_failed("run", err)
    except httpx.HTTPError as err:
        return _api_failed("run", f"cannot reach the API: {err} (is `macb up` running?)")


def cmd_ls(args: argparse.Namespace) -> int:
    import httpx

    from services.api.client import ApiError

    try:
        with _api_client(args) as api:
            exps = api.experiments(limit=args.limit)["experiments"]
    except (ApiError, httpx.HTTPError) as err:
        return _api_failed("ls", err)
    if not exps:
        print("no experiments")
    for e in exps:
        counts = ", ".join(f"{v} {k}" for k, v in e["counts"].items())
        print(f"{e['id']}  {e['status']:<9}  {e['name']}  ({counts})")
        for r in e["runs"]:
            point = " ".join(f"{k}={v}" for k, v in r["point"].items())
            p = r["progress"]
            print(
                f"  {r['id']:<28} {r['status']:<9} seed={r['seed']:<4} {point:<16} "
                f"episode {p['episode']}/{p['episodes']}"
                + (f"  {r['reason']}" if r["reason"] else "")
            )
    return 0


def _curves_from_store(db: str, experiment: str, metric: str) -> dict[str, Any] | None:
    """`plot --db`: the curves straight from a store file, no API needed."""
    from services.api.store import Store
    from services.api.views import curves

    store = Store(db)
    try:
        return curves(store, experiment, [metric])
    finally:
        store.close()


def cmd_plot(args: argparse.Namespace) -> int:
    import httpx

    from services.api.client import ApiError
    from services.api.plot import plot_curves

    if args.db:
        data = _curves_from_store(args.db, args.experiment, args.metric)
        if data is None:
            print(f"macb plot: no experiment {args.experiment!r} in {args.db}", file=sys.stderr)
            return 1
    else:
        try:
            with _api_client(args) as api:
                data = api.curves(args.experiment, [args.metric])
        except (ApiError, httpx.HTTPError) as err:
            return _api_failed("plot", err)
    out = plot_curves(data, args.metric, Path(args.output))
    print(f"wrote {out}")
    return 0
