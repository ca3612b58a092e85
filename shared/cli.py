"""The `macb` command. Subcommands are small wrappers over library functions.

Thread settings are chosen here, before numpy or torch load: every process of the
platform shares 2 cores with the others, and BLAS threads fighting torch's threads
cost up to 40% (benchmarks/bench_e2e.py: the one-process trainer ran 69 steps/s with
numpy's default BLAS threads, 78 with one). `--threads` still sets torch's own.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402 (after the thread settings, on purpose)
import logging  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import yaml  # noqa: E402

from shared.config import ConfigError, TrainConfig, load_config, make_config  # noqa: E402


def _add_config_flags(p: argparse.ArgumentParser) -> None:
    """One flag per config key (underscores become dashes); each overrides the file."""
    group = p.add_argument_group("config keys (override --config)")
    for name, field in TrainConfig.model_fields.items():
        default = field.default
        if isinstance(default, tuple):
            default = ",".join(map(str, default))
        group.add_argument(
            f"--{name.replace('_', '-')}",
            dest=f"cfg_{name}",
            metavar=name.upper(),
            default=None,
            help=f"{field.description or ''} (default: {default})".strip(),
        )


def _overrides(args: argparse.Namespace) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name in TrainConfig.model_fields:
        raw = getattr(args, f"cfg_{name}")
        if raw is None:
            continue
        if name == "hidden":
            out[name] = [s.strip() for s in raw.split(",") if s.strip()]
        elif name in ("task", "algo", "explore", "hash", "key", "reward"):
            out[name] = raw  # strings stay strings ("none" must not become null)
        else:
            out[name] = yaml.safe_load(raw)
    return out


def resolve_config(args: argparse.Namespace) -> TrainConfig:
    overrides = _overrides(args)
    if args.config:
        return load_config(args.config, overrides)
    return make_config(overrides)


def cmd_train(args: argparse.Namespace) -> int:
    from shared.trainer import train

    try:
        cfg = resolve_config(args)
    except (ConfigError, OSError) as err:
        print(f"macb train: invalid config: {err}", file=sys.stderr)
        return 2
    out = Path(args.out)
    rows = train(cfg, out, progress=not args.quiet)
    last = rows[-1] if rows else {}
    print(
        f"done: {cfg.episodes} episodes, final success {last.get('success_rate', 0):.2f}, "
        f"{last.get('steps_per_sec', 0):.1f} env steps/s "
        f"({last.get('train_steps_per_sec', 0):.1f} without evaluation); results in {out}/"
    )
    return 0


SERVICES = ("router", "counter", "learner", "actor", "evaluator", "api")


def cmd_serve(args: argparse.Namespace) -> int:
    """Run one service in the foreground until SIGTERM / Ctrl-C."""
    import os
    import socket

    from shared.bus import DEFAULT_ENDPOINT, default_connect

    if args.role == "router":
        from services.router.main import serve

        serve(args.listen or [os.environ.get("MACB_ZENOH_LISTEN", DEFAULT_ENDPOINT)])
        return 0
    if args.role == "api":
        return serve_api(args)
    import importlib

    module = importlib.import_module(f"services.{args.role}.main")
    service_id = args.id or f"{args.role}-{socket.gethostname()}-{os.getpid()}"
    connect = args.connect or default_connect()
    service = module.make_service(service_id, connect, Path(args.data_dir))
    service.install_signal_handlers()
    service.serve_forever()
    return 0


def serve_api(args: argparse.Namespace) -> int:
    """`macb serve api`: the HTTP API (uvicorn) with its scheduler and store."""
    from services.api.main import Settings, serve

    overrides: dict[str, Any] = {"data_dir": Path(args.data_dir)}
    if args.listen_http:
        host, _, port = args.listen_http.rpartition(":")
        if not host or not port.isdigit():
            print(f"macb serve api: --listen-http wants HOST:PORT, not {args.listen_http}")
            return 2
        overrides.update(host=host.strip("[]"), port=int(port))
    if args.db:
        overrides["db"] = Path(args.db)
    if args.connect:
        overrides["connect"] = args.connect
    if args.id:
        overrides["service_id"] = args.id
    return serve(Settings(**overrides))


def follow_run(bus, cfg: TrainConfig, actors: int, out: Path | None, quiet: bool) -> int:
    """Start a run on the cluster, follow it to the end, write its metrics; exit code."""
    import json

    from tqdm import tqdm

    from shared.control import NoFreeServices, send_stop, start_run
    from shared.metrics import ALL_FIELDS
    from shared.trainer import MetricsWriter

    writer = None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "config.json").write_text(json.dumps(cfg.model_dump(mode="json"), indent=2) + "\n")
        writer = MetricsWriter(out, ALL_FIELDS)
    bar = tqdm(total=cfg.episodes, unit="ep", disable=quiet, desc=f"{cfg.task} {cfg.algo}")

    def on_row(row: dict) -> None:
        if writer:
            writer.write(row)
        bar.update(row["episode"] - bar.n)
        bar.set_postfix(success=f"{row['success_rate']:.2f}", sps=f"{row['steps_per_sec']:.0f}")

    try:
        watch = start_run(bus, cfg, actors=actors, on_row=on_row)
    except NoFreeServices as err:
        print(f"macb: cannot start the run: {err}", file=sys.stderr)
        return 1
    print(f"run {watch.run} started on {watch.assign}", file=sys.stderr)
    try:
        state = watch.wait()
    except KeyboardInterrupt:
        send_stop(bus, watch.run, "interrupted")
        state = "stopped"
    finally:
        bar.close()
        if writer:
            writer.close()
    rows = watch.rows
    last = rows[-1] if rows else {}
    print(
        f"run {watch.run} {state}: {len(rows)} evaluation points, final success "
        f"{last.get('success_rate', 0):.2f}, {last.get('steps_per_sec', 0):.1f} env steps/s"
        + (f"; results in {out}/" if out else ""),
        file=sys.stderr,
    )
    if state == "failed":
        print(f"failure: {watch.failure()}", file=sys.stderr)
    return 0 if state == "completed" else 1


def cmd_start(args: argparse.Namespace) -> int:
    from shared.bus import Bus, default_connect

    try:
        cfg = resolve_config(args)
    except (ConfigError, OSError) as err:
        print(f"macb start: invalid config: {err}", file=sys.stderr)
        return 2
    with Bus(args.connect or default_connect()) as bus:
        return follow_run(bus, cfg, args.actors, Path(args.out) if args.out else None, args.quiet)


def cmd_stop(args: argparse.Namespace) -> int:
    if not args.bus:
        return _api_stop(args)
    from shared.bus import Bus, default_connect
    from shared.control import send_stop

    with Bus(args.connect or default_connect()) as bus:
        send_stop(bus, args.id)
    print(f"sent stop for run {args.id} on the bus")
    return 0


# ---------------------------------------------------------------- API clients
def _api_client(args: argparse.Namespace):
    from services.api.client import ApiClient

    return ApiClient(getattr(args, "api", None))


def _api_failed(cmd: str, err: Exception) -> int:
    print(f"macb {cmd}: {err}", file=sys.stderr)
    return 1


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


def experiment_body(args: argparse.Namespace) -> dict[str, Any]:
    """The POST /experiments body from a config file, flags, --seeds and --grid."""
    body: dict[str, Any] = {}
    if getattr(args, "config", None):
        text = Path(args.config).read_text()
        try:
            data = yaml.safe_load(text) or {}
        except yaml.YAMLError as err:
            raise ConfigError(f"{args.config}: not valid YAML/JSON: {err}") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{args.config}: a config is a mapping of keys to values")
        body.update(data)
    body.update(_overrides(args))
    make_config({k: v for k, v in body.items() if k in TrainConfig.model_fields})
    if args.seeds:
        body.pop("seed", None)
        body["seeds"] = args.seeds
    grid: dict[str, list] = {}
    for item in args.grid or []:
        key, _, values = item.partition("=")
        if key not in ("beta", "k") or not values:
            raise ConfigError(f"--grid {item}: use beta=V1,V2,... or k=V1,V2,...")
        grid[key] = [yaml.safe_load(v) for v in values.split(",") if v.strip()]
    if grid:
        body["grid"] = grid
    if args.name:
        body["name"] = args.name
    body["actors"] = args.actors
    return body


def write_results(
    api, exp: dict[str, Any], out: Path, plot: bool = True, data_dir: Path | None = None
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


def run_via_api(
    api, body: dict[str, Any], out: Path | None, quiet: bool, data_dir: Path | None = None
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
    for run in exp["runs"]:
        last = run["live"].get("eval") or {}
        print(
            f"run {run['id']} {run['status']}: {run['points']} evaluation points, final success "
            f"{last.get('success_rate', 0):.2f}, {last.get('steps_per_sec', 0):.1f} env steps/s"
            + (f" ({run['reason']})" if run["reason"] else ""),
            file=sys.stderr,
        )
    if out is not None:
        write_results(api, exp, out, data_dir=data_dir)
        print(f"results in {out}/ (metrics.csv, plot.png)", file=sys.stderr)
    print(f"experiment {exp['id']} {exp['status']}", file=sys.stderr)
    return 0 if exp["status"] == "completed" else 1


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


def cmd_plot(args: argparse.Namespace) -> int:
    import httpx

    from services.api.client import ApiError
    from services.api.plot import plot_curves

    if args.db:
        from services.api.store import Store
        from services.api.views import curves

        store = Store(args.db)
        try:
            data = curves(store, args.experiment, [args.metric])
        finally:
            store.close()
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


def cmd_ps(args: argparse.Namespace) -> int:
    from shared.bus import Bus, default_connect
    from shared.control import discover

    with Bus(args.connect or default_connect()) as bus:
        infos = discover(bus)
    for i in infos:
        print(
            f"{i['role']:<10} {i['id']:<24} run={i.get('run') or '-'} rejects={i['rejects_total']}"
        )
    if not infos:
        print("no services answer (is `macb up` running?)")
    return 0


def cmd_up(args: argparse.Namespace) -> int:
    import signal
    import threading

    from shared.bus import Bus
    from shared.cluster import Cluster, cluster_plan
    from shared.control import discover

    cfg = body = None
    if args.run:
        try:
            cfg = load_config(args.run, _overrides(args))
            body = experiment_body(
                argparse.Namespace(**{**vars(args), "config": args.run, "grid": None, "name": None})
            )
        except (ConfigError, OSError) as err:
            print(f"macb up: invalid config: {err}", file=sys.stderr)
            return 2
    data_dir = Path(args.data_dir)
    api_addr = None if args.no_api else f"127.0.0.1:{args.api_port}"
    plan = cluster_plan(args.actors, args.endpoint, str(data_dir), api=api_addr)
    cluster = Cluster(plan, data_dir / "logs", echo=not args.quiet_services)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    code = 0
    api = None
    try:
        cluster.start()
        print(
            f"cluster up: {', '.join(s.name for s in plan)}; logs in {data_dir}/logs",
            file=sys.stderr,
        )
        with Bus([args.endpoint]) as bus:
            deadline = time.monotonic() + 60
            while len(discover(bus)) < len(plan) - 1 and not stop.is_set():
                if time.monotonic() > deadline or cluster.dead():
                    print(f"services did not come up (dead: {cluster.dead()})", file=sys.stderr)
                    return 1
                time.sleep(0.2)
            if api_addr is not None and not stop.is_set():
                from services.api.client import ApiClient

                api = ApiClient(f"http://{api_addr}")
                try:
                    api.wait_healthy(60, alive=lambda: not cluster.dead())
                except TimeoutError as err:
                    print(f"{err} (dead: {cluster.dead()})", file=sys.stderr)
                    return 1
                print(
                    f"dashboard: {api.url}/   API docs: {api.url}/docs   "
                    f"store: {data_dir}/api.sqlite3",
                    file=sys.stderr,
                )
            if cfg is not None and not stop.is_set():
                out = Path(args.out) if args.out else None
                if api is not None:
                    work = lambda: run_via_api(api, body, out, args.quiet, data_dir)  # noqa: E731
                else:
                    work = lambda: follow_run(bus, cfg, args.actors, out, args.quiet)  # noqa: E731
                runner = threading.Thread(
                    target=lambda: setattr(runner, "code", work()), daemon=True
                )
                runner.start()
                while runner.is_alive() and not stop.is_set():
                    runner.join(0.2)
                    if cluster.dead():
                        print(f"service(s) died: {cluster.dead()}", file=sys.stderr)
                        stop.set()
                code = getattr(runner, "code", 1)
                if api is not None:
                    print(
                        f"the dashboard was at {api.url}/ ; the experiment and every metric "
                        f"point are kept in {data_dir}/api.sqlite3: "
                        f"`macb up --data-dir {data_dir}` shows them again",
                        file=sys.stderr,
                    )
            else:
                print(
                    "waiting for runs (macb run CONFIG, or macb start CONFIG on the bus); "
                    "Ctrl-C stops the cluster",
                    file=sys.stderr,
                )
                while not stop.wait(0.5):
                    if cluster.dead():
                        print(f"service(s) died: {cluster.dead()}", file=sys.stderr)
                        code = 1
                        break
    finally:
        if api is not None:
            api.close()
        cluster.stop()
        print("cluster stopped", file=sys.stderr)
    return code


API_HELP = "API base URL (default: MACB_API_URL or http://127.0.0.1:8000)"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="macb",
        description="Multi-agent count-based exploration (MACB): train DDPG / MADDPG agents "
        "with SimHash count bonuses on sparse particle tasks.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser(
        "train",
        help="run one experiment in this process",
        description="Run one experiment in one process and write DIR/metrics.csv, "
        "DIR/metrics.jsonl, DIR/config.json and DIR/checkpoint.pt. Keys come from --config "
        "(YAML or JSON) and are overridden by flags.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--config", metavar="FILE", help="YAML/JSON config file")
    p.add_argument("--out", metavar="DIR", default="runs/train", help="output directory")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_config_flags(p)
    p.set_defaults(func=cmd_train)

    s = sub.add_parser(
        "serve",
        help="run one service of the cluster (router, counter, learner, actor, evaluator, api)",
        description="Run one service in the foreground. Services connect as Zenoh clients to "
        "the router (MACB_ZENOH_CONNECT or --connect, default tcp/127.0.0.1:7447), announce "
        "themselves with a liveliness token and wait for runs on macb/control/start.",
    )
    s.add_argument("role", choices=SERVICES)
    s.add_argument("--id", help="service id (default: role-host-pid); actors need distinct ids")
    s.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint(s)")
    s.add_argument("--listen", action="append", metavar="ENDPOINT", help="router only: listen on")
    s.add_argument("--data-dir", default="data", help="where snapshots and checkpoints go")
    s.add_argument(
        "--listen-http",
        metavar="HOST:PORT",
        help="api only: HTTP address (default 127.0.0.1:8000; a non-loopback address "
        "needs MACB_API_TOKEN)",
    )
    s.add_argument(
        "--db", metavar="FILE", help="api only: SQLite store (default DATA_DIR/api.sqlite3)"
    )
    s.set_defaults(func=cmd_serve)

    st = sub.add_parser(
        "start",
        help="start a run on a running cluster and follow it to the end",
        description="Assign free services, start a run with this config, show its progress, "
        "and write DIR/metrics.csv and DIR/metrics.jsonl from the evaluation points.",
    )
    st.add_argument("--config", metavar="FILE", help="YAML/JSON config file")
    st.add_argument("--actors", type=int, default=1, help="actors to use")
    st.add_argument("--out", metavar="DIR", help="write metrics here")
    st.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint")
    st.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_config_flags(st)
    st.set_defaults(func=cmd_start)

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
    _add_config_flags(rn)
    rn.set_defaults(func=cmd_run)

    ls = sub.add_parser("ls", help="list experiments and their runs (through the API)")
    ls.add_argument("--api", metavar="URL", help=API_HELP)
    ls.add_argument("--limit", type=int, default=20, help="newest N experiments")
    ls.set_defaults(func=cmd_ls)

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

    ps = sub.add_parser("ps", help="list live services and the runs they serve")
    ps.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint")
    ps.set_defaults(func=cmd_ps)

    up = sub.add_parser(
        "up",
        help="start the local cluster (router, counter, learner, evaluator, actors, API)",
        description="Start every service as a local process with the same commands "
        "docker-compose.yml runs, the API last (its dashboard on 127.0.0.1:8000). With "
        "--run CONFIG, run that experiment through the API, write its results and stop; "
        "otherwise serve until Ctrl-C / SIGTERM. No process outlives this command.",
    )
    up.add_argument("--actors", type=int, default=1, help="actor processes")
    up.add_argument("--endpoint", default="tcp/127.0.0.1:7447", help="router endpoint")
    up.add_argument("--data-dir", default="data", help="snapshots, checkpoints, logs")
    up.add_argument("--run", metavar="CONFIG", help="run this experiment, then stop")
    up.add_argument("--seeds", type=int, nargs="+", metavar="SEED", help="with --run: seeds")
    up.add_argument("--api-port", type=int, default=8000, help="the API's port on 127.0.0.1")
    up.add_argument("--no-api", action="store_true", help="no API (runs go on the bus)")
    up.add_argument("--out", metavar="DIR", help="with --run: write metrics here")
    up.add_argument("--quiet", action="store_true", help="no progress bar")
    up.add_argument("--quiet-services", action="store_true", help="service logs to files only")
    _add_config_flags(up)
    up.set_defaults(func=cmd_up)
    return parser


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)  # not a line per API call
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
