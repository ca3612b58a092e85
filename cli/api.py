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
from pydantic import ValidationError

from cli.config_flags import (
    COMMA_LIST_FIELDS,
    add_config_flags,
    at_least_one,
    config_overrides,
    read_flag_value,
)
from cli.local import add_group_flags
from cli.security import add_security_flags
from shared.config import (
    ConfigError,
    TrainConfig,
    format_errors,
    read_config_file,
    read_yaml_file,
)
from shared.metrics import CURVE_FIELDS

if TYPE_CHECKING:
    from cli.local import LocalRun
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
    add_security_flags(sp)
    sp.set_defaults(func=cmd_stop)


def add_run_parser(sub: argparse._SubParsersAction) -> None:
    rn = sub.add_parser(
        "run",
        help="submit an experiment to the API and follow it to the end",
        description="Submit CONFIG (a YAML/JSON config, keys overridden by flags) as an "
        "experiment: one run per arm, grid point and seed, queued until services are free. "
        "Shows a progress bar until every run has ended; Ctrl-C stops the experiment.",
    )
    rn.add_argument("config", metavar="CONFIG", help="YAML/JSON config file")
    rn.add_argument("--seeds", type=int, nargs="+", metavar="SEED", help="one run per seed")
    rn.add_argument(
        "--grid",
        action="append",
        metavar="KEY=V1,V2",
        help="sweep any config key but the seed (repeat for more keys; the runs are the "
        "product): --grid explore=none,dis-macb,cen-macb --grid beta=0.2,0.8; values are "
        "read like the key's flag (--hidden takes lists: --grid hidden=[64,64],[32])",
    )
    rn.add_argument(
        "--arms",
        metavar="FILE",
        help="a YAML list of named partial configs over CONFIG, e.g. "
        "'- {name: cen-macb, explore: cen-macb}' and '- {name: control, explore: constant}'; "
        "each arm runs every seed (and grid point)",
    )
    rn.add_argument("--name", help="experiment name")
    rn.add_argument("--actors", type=at_least_one, default=1, help="actors per run")
    rn.add_argument("--api", metavar="URL", help=API_HELP)
    rn.add_argument("--out", metavar="DIR", help="write metrics.csv and plot.png here")
    rn.add_argument("--detach", action="store_true", help="submit, print the id and return")
    rn.add_argument(
        "--local",
        action="store_true",
        help="no API or cluster: run every run in this process, as run groups (runs that "
        "share task, network and update settings train as one; each run's results are "
        "those it gives alone), each in OUT/<arm>-s<seed>/ (OUT default runs/local); "
        "the same command again continues where it stopped",
    )
    add_group_flags(rn)
    rn.add_argument("--quiet", action="store_true", help="no progress bar")
    add_config_flags(rn, "CONFIG")
    rn.set_defaults(func=cmd_run)


def add_ls_parser(sub: argparse._SubParsersAction) -> None:
    ls = sub.add_parser(
        "ls",
        help="list experiments and their runs (through the API)",
        description="List the API's newest experiments, each with its runs: status, "
        "progress and points.",
    )
    ls.add_argument("--api", metavar="URL", help=API_HELP)
    ls.add_argument("--limit", type=at_least_one, default=20, help="newest N experiments")
    ls.set_defaults(func=cmd_ls)


def add_plot_parser(sub: argparse._SubParsersAction) -> None:
    pl = sub.add_parser(
        "plot",
        help="draw an experiment's learning curves (mean over seeds with a band) to a PNG",
        description="Draw an experiment's curves of one metric (each arm's mean over its "
        "seeds, with a band) to a PNG, from the API or, with --db, from a store file (only "
        "read).",
    )
    pl.add_argument("experiment", metavar="EXPERIMENT_ID")
    pl.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="FILE.png",
        help="the figure; its suffix names the format (png, svg, pdf, ...)",
    )
    pl.add_argument(
        "--metric",
        default="success_rate",
        choices=CURVE_FIELDS,
        metavar="METRIC",
        help=f"the metric to plot: one of {', '.join(CURVE_FIELDS)}",
    )
    pl.add_argument("--api", metavar="URL", help=API_HELP)
    pl.add_argument("--db", metavar="FILE", help="read this store instead of asking the API")
    pl.set_defaults(func=cmd_plot)


# ---------------------------------------------------------------- helpers
def _api_client(args: argparse.Namespace) -> ApiClient:
    from services.api.client import ApiClient

    return ApiClient(getattr(args, "api", None))


def _api_failed(cmd: str, err: Exception | str) -> int:
    """Say why the API did not answer: 2 for a URL of no form (bad input), 1 otherwise,
    naming the URL tried when the API could not be reached."""
    import httpx

    if isinstance(err, (httpx.UnsupportedProtocol, httpx.InvalidURL)):
        print(f"macb {cmd}: --api (or MACB_API_URL): not an http(s) URL: {err}", file=sys.stderr)
        return 2
    if isinstance(err, httpx.RequestError):
        try:
            url = err.request.url
            where = f" at {url.scheme}://{url.netloc.decode()}"
        except RuntimeError:  # (no request was built)
            where = ""
        err = (
            f"cannot reach the API{where}: {err} (is `macb up` running? --api URL or "
            "MACB_API_URL says where)"
        )
    print(f"macb {cmd}: {err}", file=sys.stderr)
    return 1


def _read_config_file(path: str) -> dict[str, Any]:
    """The file's mapping as written: the body sends every key on (a file may also hold
    the experiment's `seeds`, `grid` or `name`), and the API judges what is not config."""
    return read_config_file(path)


def _split_values(text: str) -> list[str]:
    """`a,b,[1,2]` as ["a", "b", "[1,2]"]: commas split, except inside brackets."""
    parts, depth, current = [], 0, ""
    for ch in text:
        depth += {"[": 1, "{": 1, "]": -1, "}": -1}.get(ch, 0)
        if ch == "," and depth == 0:
            parts.append(current)
            current = ""
        else:
            current += ch
    parts.append(current)
    return [p.strip() for p in parts if p.strip()]


def _grid_value(key: str, raw: str) -> Any:
    """One grid value, read as the key's flag reads it (strings stay strings for string
    fields, the rest is YAML), except lists, which are YAML lists here: `[64,64]`."""
    if key in COMMA_LIST_FIELDS:
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError:
            value = None
        if not isinstance(value, list):
            raise ConfigError(f"--grid {key}: give each value as a list: {key}=[64,64],[32]")
        return value
    try:
        return read_flag_value(key, raw)
    except ConfigError as err:
        raise ConfigError(f"--grid {key}={raw}: {str(err).split(': ', 1)[-1]}") from None


def _grid(items: list[str] | None) -> dict[str, list]:
    """`--grid explore=none,cen-macb --grid beta=0.2,0.8` as {"explore": ["none",
    "cen-macb"], "beta": [0.2, 0.8]}. A key that is not a config key, a seed, or a key
    given twice is refused here, before the API is asked."""
    grid: dict[str, list] = {}
    for item in items or []:
        key, _, values = item.partition("=")
        key = key.strip().replace("-", "_")
        if key in ("seed", "seeds"):
            raise ConfigError(f"--grid {item}: the seed is not a grid key: use --seeds 0 1 2")
        if key not in TrainConfig.model_fields:
            raise ConfigError(f"--grid {item}: {key!r} is not a config key (misspelt?)")
        if key in grid:
            raise ConfigError(f"--grid {key}: given twice; list every value in one --grid")
        parsed = [_grid_value(key, v) for v in _split_values(values)]
        if not parsed:
            raise ConfigError(f"--grid {item}: no values; use {key}=V1,V2,...")
        grid[key] = parsed
    return grid


def read_arms(path: str) -> list[dict[str, Any]]:
    """An arms file: a YAML list of mappings, each with a `name` (or a mapping whose
    `arms` is that list). The keys are the API's to judge; only the shape is checked."""
    data = read_yaml_file(path, "an arms file")
    if isinstance(data, dict) and "arms" in data:
        data = data["arms"]
    if not isinstance(data, list) or not data:
        raise ConfigError(f"{path}: an arms file is a list of named partial configs")
    for i, arm in enumerate(data):
        if not isinstance(arm, dict) or not isinstance(arm.get("name"), str):
            raise ConfigError(f"{path}: arm {i} is not a mapping with a `name`")
    return data


def _check_base(config: dict[str, Any], varied: bool) -> None:
    """Refuse a bad base config before the API is asked. With arms or a grid, the base
    alone may break a cross-field rule (an arm may set the algo): only each run's config
    must be valid, which the API checks; field errors are still refused here."""
    try:
        TrainConfig.model_validate(config)
    except ValidationError as err:
        if not varied or any(e["loc"] for e in err.errors()):
            raise ConfigError(format_errors(err)) from None


def experiment_body(args: argparse.Namespace) -> dict[str, Any]:
    """The POST /experiments body from a config file, flags, --seeds, --grid and --arms
    (the flags replace what the file says: `--seeds` or `--seed` its `seeds`)."""
    body: dict[str, Any] = {}
    if getattr(args, "config", None):
        body.update(_read_config_file(args.config))
    overrides = config_overrides(args)
    if "seed" in overrides:
        body.pop("seeds", None)  # `--seed 5` over a file's seeds: that one seed
    body.update(overrides)
    grid = _grid(args.grid)
    if grid:
        in_file = body.get("grid")
        body["grid"] = {**(in_file if isinstance(in_file, dict) else {}), **grid}
    if getattr(args, "arms", None):
        body["arms"] = read_arms(args.arms)
    config = {k: v for k, v in body.items() if k in TrainConfig.model_fields}
    _check_base(config, varied=bool(body.get("grid") or body.get("arms")))
    if args.seeds:
        body.pop("seed", None)
        body["seeds"] = args.seeds
    if args.name:
        body["name"] = args.name
    body["actors"] = args.actors
    return body


def write_results(
    api: ApiClient, exp: dict[str, Any], out: Path, plot: bool = True, data_dir: Path | None = None
) -> list[Path]:
    """Each run's metrics.csv, metrics.jsonl, config.json, provenance.json (what its
    learner ran on, as it reported at its latest start) and, with the cluster's data
    dir, the learner's checkpoint.pt (and best.pt, the best point's, for a run with
    `early_stop`) in out/ for one run or out/<run id>/ for several,
    then every run's points in out/metrics.csv (with `arm`, `seed`, `run` columns);
    out/plot.png, every arm overlaid."""
    import json
    import shutil

    from shared.persist import provenance

    out.mkdir(parents=True, exist_ok=True)
    written = []
    for run in exp["runs"]:
        d = out if len(exp["runs"]) == 1 else out / run["id"]
        d.mkdir(parents=True, exist_ok=True)
        (d / "metrics.csv").write_text(api.metrics_csv(run["id"]))
        points = api.all_points(run["id"])  # every page: a run has more than one
        with (d / "metrics.jsonl").open("w") as f:
            for p in points:
                f.write(json.dumps({k: v for k, v in p.items() if k != "seq"}) + "\n")
        (d / "config.json").write_text(json.dumps(run["config"], indent=2) + "\n")
        if start := provenance.reported(run):
            provenance.write(d / provenance.FILE, [start])
        written.append(d / "metrics.csv")
        for name in ("checkpoint.pt", "best.pt"):  # (best.pt: a run with early_stop)
            kept = data_dir / "learner" / run["id"] / name if data_dir else None
            if kept is not None and kept.exists():
                shutil.copyfile(kept, d / name)
    if len(exp["runs"]) > 1:
        (out / "metrics.csv").write_text(api.experiment_csv(exp["id"]))
        written.append(out / "metrics.csv")
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
    from cli.view import learned

    points = {r["id"]: api.all_points(r["id"]) for r in exp["runs"]}
    for line in learned(exp, points):
        print(line, file=sys.stderr)
    if out is not None:
        write_results(api, exp, out, data_dir=data_dir)
        print(f"results in {out}/ (metrics.csv, plot.png)", file=sys.stderr)
    print(f"experiment {exp['id']} {exp['status']}", file=sys.stderr)
    return 0 if exp["status"] == "completed" else 1


# ---------------------------------------------------------------- commands
def cmd_stop(args: argparse.Namespace) -> int:
    if not args.bus:
        return _api_stop(args)
    return stop_on_bus(args)


def stop_on_bus(args: argparse.Namespace) -> int:
    """`macb stop --bus RUN`: for runs started with `macb start`, which the API never saw."""
    from shared.net.bus import Bus, default_connect
    from shared.net.control import send_stop

    with Bus(args.connect or default_connect()) as bus:
        send_stop(bus, args.id)
    print(f"sent stop for run {args.id} on the bus")
    return 0


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
        return _api_failed("stop", err)
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    import httpx

    from services.api.client import ApiError

    try:
        body = experiment_body(args)
    except (ConfigError, OSError) as err:
        print(f"macb run: invalid config: {err}", file=sys.stderr)
        return 2
    if why := _run_flags_error(args):
        print(f"macb run: {why}", file=sys.stderr)
        return 2
    if args.local:
        try:
            expanded = _expand(body)
        except ConfigError as err:
            print(f"macb run: invalid config: {err}", file=sys.stderr)
            return 2
        return _run_local(args, *expanded)
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
        # The API checks the runs (a custom task may be importable only where it runs);
        # when it cannot be asked, a config that is invalid here is the first thing to say.
        try:
            _expand(body)
        except ConfigError as why:
            print(f"macb run: invalid config: {why} (checked here: the API did not "
                  f"answer: {err})", file=sys.stderr)  # fmt: skip
            return 2
        return _api_failed("run", err)


def _expand(body: dict[str, Any]) -> tuple[str, list[int], list[LocalRun]]:
    """The experiment's name, seeds and runs, as the API and `--local` expand them;
    ConfigError ('field: reason') when a run's config is not valid."""
    from pydantic import ValidationError

    from cli.local import expand_body

    try:
        return expand_body(body)
    except ValidationError as err:  # (before ValueError, which it is): field: reason
        raise ConfigError(format_errors(err)) from None
    except ValueError as err:
        raise ConfigError(str(err)) from None


def _run_flags_error(args: argparse.Namespace) -> str | None:
    """Flags of the other way of running, which it would ignore: with --local the API's
    (--detach, --api, --actors), without it --local's (--group-size, --jobs)."""
    if args.local:
        api_only = [("--detach", args.detach), ("--api", args.api), ("--actors", args.actors != 1)]
        if given := [flag for flag, on in api_only if on]:
            return (
                f"{', '.join(given)}: not with --local (its runs train in this process, "
                "without the API or a cluster's actors); drop it"
            )
    elif given := [f for f in ("--group-size", "--jobs") if getattr(args, f[2:].replace("-", "_"))]:
        return f"{', '.join(given)}: only with --local (the API's services run the runs)"
    return None


def _run_local(args: argparse.Namespace, name: str, seeds: list[int], runs: list[LocalRun]) -> int:
    """`macb run --local`: the experiment's runs (`_expand`) as run groups in this
    process."""
    from cli.local import (
        group_flag_error,
        local_experiment,
        local_points,
        run_groups,
    )

    if error := group_flag_error(args):
        print(f"macb run: {error}", file=sys.stderr)
        return 2
    out = Path(args.out or "runs/local")
    code = run_groups(runs, out, args.group_size, args.quiet, jobs=args.jobs)
    exp = local_experiment(name, seeds, runs, out)
    points = local_points(runs, out)
    for run in exp["runs"]:
        last = points[run["id"]][-1] if points[run["id"]] else {}
        print(
            f"run {run['id']} {run['status']}: {len(points[run['id']])} evaluation points, "
            f"final success {last.get('success_rate', 0):.2f}",
            file=sys.stderr,
        )
    if len(runs) > 1:
        from services.api.plot import plot_curves
        from services.api.views import curves_of

        described = [{**r, "point": {}} for r in exp["runs"]]
        curves = curves_of(exp["id"], name, described, points, ["success_rate"])
        plot_curves(curves, "success_rate", out / "plot.png")
    print(f"results in {out}/", file=sys.stderr)
    return code


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
            p = r["progress"]
            print(
                f"  {r['id']:<28} {r['status']:<9} seed={r['seed']:<4} "
                f"arm={r.get('arm', ''):<24} episode {p['episode']}/{p['episodes']}"
                + (f"  attempt {r['attempts']}" if r.get("attempts", 1) > 1 else "")
                + (f"  {r['reason']}" if r["reason"] else "")
            )
    return 0


def _curves_from_store(db: str, experiment: str, metric: str) -> dict[str, Any] | None:
    """`plot --db`: the curves straight from a store file, no API needed."""
    from cli.store_file import store_copy
    from services.api.views import curves

    with store_copy(db) as store:  # only read: NotAStore if it is none
        return curves(store, experiment, [metric])


def cmd_plot(args: argparse.Namespace) -> int:
    import httpx

    from cli.runs_folder import unwritable
    from services.api.client import ApiError
    from services.api.plot import PlotFormatError, plot_curves

    if why := unwritable(Path(args.output).parent):
        print(f"macb plot: -o {args.output}: cannot write there ({why})", file=sys.stderr)
        return 2
    if args.db:
        from cli.store_file import NotAStore, store_file_error

        if why := store_file_error(args.db):  # (a Store would make it, and its folder)
            print(f"macb plot: {why}", file=sys.stderr)
            return 2

        try:
            data = _curves_from_store(args.db, args.experiment, args.metric)
        except NotAStore as err:
            print(f"macb plot: {err}", file=sys.stderr)
            return 2
        if data is None:
            print(f"macb plot: no experiment {args.experiment!r} in {args.db}", file=sys.stderr)
            return 1
    else:
        try:
            with _api_client(args) as api:
                data = api.curves(args.experiment, [args.metric])
        except (ApiError, httpx.HTTPError) as err:
            return _api_failed("plot", err)
    try:
        out = plot_curves(data, args.metric, Path(args.output))
    except PlotFormatError as err:
        print(f"macb plot: {args.output}: {err}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0
