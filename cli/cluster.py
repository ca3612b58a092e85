"""The commands that run or talk to the cluster on the bus: `serve`, `up`, `start`, `ps`,
and `stop --bus` (the `stop` command itself lives with the API commands in cli.api).

`serve` is the one place a service is started from a command line: `macb up`
(cli/supervisor.py) and docker-compose.yml both run `macb serve ROLE ...`.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cli.api import experiment_body, run_via_api
from cli.config_flags import (
    add_config_flags,
    at_least_one,
    config_overrides,
    given_config_flags,
    one_run_config,
    resolve_config,
)
from cli.security import add_security_flags
from cli.supervisor import (
    Cluster,
    DidNotListen,
    PortInUse,
    check_ports,
    cluster_plan,
    host_port,
)
from shared.config import ConfigError, TrainConfig, actors_error
from shared.persist.files import data_dir_help, default_data_dir
from shared.settings import settings

if TYPE_CHECKING:
    from services.api.client import ApiClient
    from shared.net.bus import Bus

SERVICES = ("router", "counter", "learner", "actor", "evaluator", "api", "slot")


# ---------------------------------------------------------------- parsers
def add_serve_parser(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser(
        "serve",
        help="run one service of the cluster (router, counter, learner, actor, evaluator, api)",
        description="Run one service in the foreground. Services connect as Zenoh clients to "
        "the router (MACB_ZENOH_CONNECT or --connect, default tcp/127.0.0.1:7447), announce "
        "themselves with a liveliness token and wait for runs on macb/control/start. "
        "`slot` is a worker slot: a learner, an evaluator and --actors actors with ids "
        "ROLE-ID, restarted when they die (what the Slurm cluster job runs per task).",
    )
    s.add_argument("role", choices=SERVICES)
    s.add_argument(
        "--id",
        help="service id (default: role-host-pid; the router: MACB_ZENOH_USER, else "
        "`router`; the API: MACB_API_SERVICE_ID, else `api`); actors need distinct ids",
    )
    s.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="router endpoint(s); for a router: other routers to peer with",
    )
    s.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help="router only: listen on (beyond 127.0.0.0/8 only with TLS and a users file)",
    )
    s.add_argument(
        "--data-dir",
        help=data_dir_help("where snapshots, checkpoints and the api's store go")
        + "; for the api, MACB_API_DATA_DIR sets it too",
    )
    s.add_argument(
        "--listen-http",
        metavar="HOST:PORT",
        help="api only: HTTP address (default 127.0.0.1:8000; a non-loopback address "
        "needs MACB_API_TOKEN)",
    )
    s.add_argument(
        "--db", metavar="FILE", help="api only: SQLite store (default DATA_DIR/api.sqlite3)"
    )
    s.add_argument("--actors", type=at_least_one, default=1, help="slot only: its actors")
    add_security_flags(s)
    s.set_defaults(func=cmd_serve)


def add_start_parser(sub: argparse._SubParsersAction) -> None:
    st = sub.add_parser(
        "start",
        help="start a run on a running cluster and follow it to the end",
        description="Assign free services, start a run with this config, show its progress, "
        "and write DIR/metrics.csv and DIR/metrics.jsonl from the evaluation points.",
    )
    st.add_argument("--config", metavar="FILE", help="YAML/JSON config file")
    st.add_argument("--actors", type=at_least_one, default=1, help="actors to use")
    st.add_argument("--out", metavar="DIR", help="write metrics here")
    st.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint")
    st.add_argument("--quiet", action="store_true", help="no progress bar")
    add_config_flags(st)
    add_security_flags(st)
    st.set_defaults(func=cmd_start)


def add_ps_parser(sub: argparse._SubParsersAction) -> None:
    ps = sub.add_parser(
        "ps",
        help="list live services and the runs they serve",
        description="Ask every service on the bus for its info and print one line each: "
        "role, id, the run it serves, messages it rejected, restarts (and each router's "
        "ACL denials).",
    )
    ps.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint")
    add_security_flags(ps)
    ps.set_defaults(func=cmd_ps)


def add_up_parser(sub: argparse._SubParsersAction) -> None:
    up = sub.add_parser(
        "up",
        help="start the local cluster (router, counter, learner, evaluator, actors, API)",
        description="Start every service as a local process with the same commands "
        "docker-compose.yml runs, the API last (its dashboard on 127.0.0.1:8000). With "
        "--run CONFIG, run that experiment through the API, write its results and stop; "
        "otherwise serve until Ctrl-C / SIGTERM. A service that dies is restarted (0.5 s "
        "backoff doubling to 10 s) and rejoins its run; one that dies 5 times in a minute "
        "stops the cluster. Run again on the same --data-dir, it resumes the runs that "
        "were running. No process outlives this command, even killed. A router or API port "
        "that something already listens on is refused before anything starts (exit 2).",
    )
    up.add_argument("--actors", type=at_least_one, default=1, help="actor processes")
    up.add_argument(
        "--slots",
        type=int,
        default=1,
        metavar="N",
        help="runs at once: N learners and evaluators, N x --actors actors, one counter "
        "(queued runs start on whichever are free); with --launcher slurm, N per node, "
        "each slot a Slurm task",
    )
    up.add_argument(
        "--group-size",
        type=int,
        default=1,
        metavar="N",
        help="the API starts up to N queued runs of one experiment as one run group when "
        "they can share one (interleave lockstep, one actor, same task and networks): "
        "one learner, actor and evaluator serve them all, each run the one-process "
        "group's (default 1: every run on its own services)",
    )
    up.add_argument(
        "--endpoint",
        default="tcp/127.0.0.1:7447",
        help="router endpoint (with --launcher slurm only its port is chosen: the job's "
        "router listens where its nodes reach it)",
    )
    up.add_argument("--data-dir", help=data_dir_help("snapshots, checkpoints, logs, the store"))
    up.add_argument("--run", metavar="CONFIG", help="run this experiment, then stop")
    up.add_argument("--seeds", type=int, nargs="+", metavar="SEED", help="with --run: seeds")
    up.add_argument("--api-port", type=int, default=8000, help="the API's port on 127.0.0.1")
    up.add_argument(
        "--no-api",
        action="store_true",
        help="no API (runs go on the bus; not with --launcher slurm, whose job runs it)",
    )
    up.add_argument("--out", metavar="DIR", help="with --run: write metrics here")
    up.add_argument("--quiet", action="store_true", help="no progress bar")
    up.add_argument("--quiet-services", action="store_true", help="service logs to files only")
    add_config_flags(up, "--run CONFIG")
    add_security_flags(up)  # --secrets DIR: TLS, each service signed in as its id
    add_up_slurm_flags(up)
    up.set_defaults(func=cmd_up)


def add_up_slurm_flags(up: argparse.ArgumentParser) -> None:
    up.add_argument(
        "--launcher",
        choices=("local", "slurm"),
        default="local",
        help="where the cluster runs: local processes (local), or one Slurm job (slurm): "
        "router and API on the first node, a counter on every node, --slots worker slots "
        "per node, each a Slurm task of --cpus-per-slot CPUs; submitted, then followed "
        "until its API answers (docs/deploy.md, 'On a Slurm cluster')",
    )
    slurm = up.add_argument_group("--launcher slurm")
    slurm.add_argument("--nodes", type=int, default=1, help="the job's nodes")
    slurm.add_argument("--cpus-per-slot", type=int, default=1, help="CPUs of each slot's task")
    slurm.add_argument(
        "--partition", help="the job's partition, or a comma-separated list (sbatch --partition)"
    )
    slurm.add_argument("--time", metavar="LIMIT", help="the job's time limit (sbatch --time)")
    slurm.add_argument("--account", help="the account charged (sbatch --account)")
    slurm.add_argument(
        "--sbatch-args",
        metavar="ARGS",
        help="more sbatch arguments, as one string (not -M/--clusters: the job is followed "
        "on the default cluster only)",
    )
    slurm.add_argument("--detach", action="store_true", help="submit and return at once")
    slurm.add_argument(
        "--wait", type=float, default=600.0, metavar="S", help="how long to wait for its API"
    )


# ---------------------------------------------------------------- serve
def cmd_serve(args: argparse.Namespace) -> int:
    """Run one service in the foreground until SIGTERM / Ctrl-C."""
    import os
    import socket

    from shared.net.bus import DEFAULT_ENDPOINT, default_connect
    from shared.net.security import BusError, Security, SecurityError

    try:  # every file and setting checked before any session opens: nothing half-starts
        sec = Security.from_env()
        if args.role == "router":
            sec.for_router().check("router")
        elif args.role != "slot":  # (a slot's services sign in as their own ids)
            sec.check("client")
    except SecurityError as err:
        print(f"macb serve {args.role}: {err}", file=sys.stderr)
        return 2
    if args.role == "router":
        from services.router.main import serve

        listen = args.listen or [settings().zenoh_listen or DEFAULT_ENDPOINT]
        try:
            serve(listen, connect=args.connect, router_id=args.id or sec.user or "router")
        except (SecurityError, BusError) as err:
            print(f"macb serve router: {err}", file=sys.stderr)
            return 2
        return 0
    if args.role == "api":
        return serve_api(args)
    if args.role == "slot":
        return serve_slot(args)
    import importlib

    module = importlib.import_module(f"services.{args.role}.main")
    service_id = args.id or f"{args.role}-{socket.gethostname()}-{os.getpid()}"
    connect = args.connect or default_connect()
    try:
        service = module.make_service(
            service_id, connect, Path(args.data_dir or default_data_dir())
        )
    except BusError as err:  # no router at `connect`: named, one line (the role with it)
        print(f"macb serve {args.role}: {err}", file=sys.stderr)
        return 2
    from services.common import stop_on_signals

    stop_on_signals(service)
    service.serve_forever()
    return 0


def serve_slot(args: argparse.Namespace) -> int:
    """`macb serve slot --id ID`: a learner, an evaluator and actors as children,
    restarted when they die (as `macb up` does), all stopped by PID on SIGTERM."""
    from cli.supervisor import slot_plan

    if not args.id or args.actors < 1:
        print("macb serve slot: give --id (the slot's name) and --actors >= 1", file=sys.stderr)
        return 2
    data_dir = Path(args.data_dir or default_data_dir())
    signed_in = bool(settings().zenoh_secrets)
    plan = slot_plan(args.id, args.actors, str(data_dir), signed_in)
    cluster = Cluster(plan, data_dir / "logs", echo=False)  # each its log file
    stop = _stop_on_signals()
    try:
        cluster.start()
        print(f"slot {args.id}: {', '.join(s.name for s in cluster.plan)}", file=sys.stderr)
        return _serve_until_stopped(cluster, stop, quiet=True)
    finally:
        cluster.stop()


def serve_api(args: argparse.Namespace) -> int:
    """`macb serve api`: the HTTP API (uvicorn) with its scheduler and store."""
    from services.api.main import Settings, serve

    overrides: dict[str, Any] = {}
    if args.data_dir:  # else MACB_API_DATA_DIR, else the per-user default
        overrides["data_dir"] = Path(args.data_dir)
    if args.listen_http:
        host, _, port = args.listen_http.rpartition(":")
        if not host or not port.isdigit():
            print(f"macb serve api: --listen-http wants HOST:PORT, not {args.listen_http}",
                  file=sys.stderr)  # fmt: skip
            return 2
        overrides.update(host=host.strip("[]"), port=int(port))
    if args.db:
        overrides["db"] = Path(args.db)
    if args.connect:
        overrides["connect"] = args.connect
    if args.id:
        overrides["service_id"] = args.id
    from cli.view import experiment_view

    return serve(Settings(**overrides), figure_view=experiment_view)


# ---------------------------------------------------------------- runs on the bus
def _metrics_writer(cfg: TrainConfig, out: Path | None) -> Any:
    """out/config.json now and a MetricsWriter for the rows to come (None: no out)."""
    import json

    from cli.trainer import MetricsWriter
    from shared.metrics import ALL_FIELDS, run_fields

    if out is None:
        return None
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(cfg.model_dump(mode="json"), indent=2) + "\n")
    return MetricsWriter(out, run_fields(cfg, ALL_FIELDS))


def follow_run(bus: Bus, cfg: TrainConfig, actors: int, out: Path | None, quiet: bool) -> int:
    """Start a run on the cluster, follow it to the end, write its metrics; exit code."""
    from tqdm import tqdm

    from shared.net.control import NoFreeServices, send_stop, start_run

    writer = _metrics_writer(cfg, out)
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
    print(f"run {watch.run} started on {watch.assign.to_wire()}", file=sys.stderr)
    try:
        state = watch.wait()
    except KeyboardInterrupt:
        send_stop(bus, watch.run, "interrupted")
        state = "stopped"
    finally:
        bar.close()
        if writer:
            writer.close()
    return _report_run_end(watch, state, out)


def _report_run_end(watch: Any, state: str, out: Path | None) -> int:
    """The run's summary line (and its failure); exit 0 only for a completed run."""
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
    if state == "completed" and last.get("stop_reason"):
        print(f"ended by its rule: {last['stop_reason']}", file=sys.stderr)
    return 0 if state == "completed" else 1


def check_actors(cfg: TrainConfig, actors: int) -> None:
    """A lockstep run has one actor: refused before anything starts, naming the key."""
    if why := actors_error(cfg, actors):
        raise ConfigError(why)


def cmd_start(args: argparse.Namespace) -> int:
    from shared.net.bus import Bus, default_connect

    try:
        cfg = resolve_config(args)
        check_actors(cfg, args.actors)
    except (ConfigError, OSError) as err:
        print(f"macb start: invalid config: {err}", file=sys.stderr)
        return 2
    with Bus(args.connect or default_connect()) as bus:
        return follow_run(bus, cfg, args.actors, Path(args.out) if args.out else None, args.quiet)


def cmd_ps(args: argparse.Namespace) -> int:
    from shared.net.bus import Bus, default_connect
    from shared.net.control import discover

    with Bus(args.connect or default_connect()) as bus:
        infos = discover(bus)
        routers = _router_stats(bus)
    for r in routers:  # routers answer only with the ACL's account (docs/deploy.md)
        acl = f"acl denied={r['denied_total']}" if r.get("acl") else "no acl"
        print(f"{'router':<10} {r['id']:<24} {acl}")
    for i in infos:
        print(
            f"{i['role']:<10} {i['id']:<24} run={i.get('run') or '-'} "
            f"rejects={i['rejects_total']} restarts={i.get('restarts', 0)}"
        )
    if not infos:
        print("no services answer (is `macb up` running?)")
    return 0


def _router_stats(bus: Bus) -> list[dict[str, Any]]:
    """Each reachable router's answer on macb/router/*: its ACL's denial counts."""
    import json

    from shared.net.bus import k_router

    out = []
    for raw in bus.get(k_router("*"), timeout=1.0):
        with contextlib.suppress(ValueError):
            out.append(json.loads(raw))
    return sorted(out, key=lambda r: str(r.get("id")))


# ---------------------------------------------------------------- up
def cmd_up(args: argparse.Namespace) -> int:
    """Start the local cluster, then run `--run CONFIG` on it or serve until a signal.

    The config is checked before any process starts, and `local_cluster` stops every
    child whichever way this returns, so no process outlives `macb up`.
    """
    for flag, value in (("--slots", args.slots), ("--group-size", args.group_size)):
        if value < 1:
            print(f"macb up: {flag} must be at least 1, not {value}", file=sys.stderr)
            return 2
    try:  # (the resolver would take port 70000 for 4464)
        host_port(args.endpoint)
    except ValueError as err:
        print(f"macb up: --endpoint: {err}", file=sys.stderr)
        return 2
    if not 1 <= args.api_port <= 65535:
        print(f"macb up: --api-port must be from 1 to 65535, not {args.api_port}", file=sys.stderr)
        return 2
    if not args.run and (run_only := _run_flags(args)):  # (taken and ignored, before)
        where = "with --run CONFIG (without it, up serves until stopped: runs come by `macb run`)"
        if args.launcher == "slurm":
            where = "not with --launcher slurm (runs go to the job's API: `macb run`)"
        print(f"macb up: {', '.join(run_only)}: {where}", file=sys.stderr)
        return 2
    if args.launcher == "slurm":
        from cli.slurm_cluster import cmd_up_slurm

        return cmd_up_slurm(args)
    slurm_only = [f for f in ("partition", "time", "account", "sbatch_args") if getattr(args, f)]
    if slurm_only or args.nodes != 1 or args.cpus_per_slot != 1 or args.detach:
        print("macb up: --nodes, --partition, ... are for --launcher slurm", file=sys.stderr)
        return 2
    try:
        cfg, body = _up_experiment(args)
    except (ConfigError, OSError) as err:
        print(f"macb up: invalid config: {err}", file=sys.stderr)
        return 2
    data_dir = Path(args.data_dir or default_data_dir())
    api_addr = None if args.no_api else f"127.0.0.1:{args.api_port}"
    endpoint, secrets = _secure_endpoint(args.endpoint)
    try:
        with local_cluster(
            args.actors,
            endpoint,
            data_dir,
            api_addr,
            echo=not args.quiet_services,
            slots=args.slots,
            secrets=secrets,
            group_size=args.group_size,
        ) as up:
            if cfg is None or body is None or up.stop.is_set():  # (both None without --run)
                return _serve_until_stopped(up.cluster, up.stop)
            code = up.run(_experiment(args, cfg, body, up.bus, up.api, data_dir))
            if up.api is not None:
                _print_where_results_stay(up.api, data_dir)
            return code
    except ClusterDidNotStart as err:
        return err.code


def _secure_endpoint(endpoint: str) -> tuple[str, str | None]:
    """With a secrets folder (--secrets / MACB_ZENOH_SECRETS), the cluster runs on TLS
    (tcp/ becomes tls/) and `macb up` itself signs in as `cli` unless told otherwise."""
    secrets = settings().zenoh_secrets
    if not secrets:
        return endpoint, None
    os.environ.setdefault("MACB_ZENOH_USER", "cli")
    if endpoint.startswith("tcp/"):
        endpoint = "tls/" + endpoint.removeprefix("tcp/")
    return endpoint, secrets


class ClusterDidNotStart(RuntimeError):
    """A service or the API did not come up (what and why is printed already); `code`:
    the exit code to end with (2: refused before anything started)."""

    def __init__(self, what: str, code: int = 1) -> None:
        super().__init__(what)
        self.code = code


@dataclass
class LocalCluster:
    """The running local cluster: its processes, a bus session, the API client (None
    without an API) and the event a signal sets."""

    cluster: Cluster
    bus: Bus
    api: ApiClient | None
    stop: threading.Event

    def run(self, work: Callable[[], int]) -> int:
        """`work`'s exit code, or 1 if a signal or a dead service ended it first."""
        return _run_while_cluster_lives(work, self.cluster, self.stop)


@contextlib.contextmanager
def local_cluster(
    actors: int,
    endpoint: str,
    data_dir: Path,
    api_addr: str | None,
    echo: bool = True,
    slots: int = 1,
    secrets: str | None = None,
    group_size: int = 1,
) -> Iterator[LocalCluster]:
    """Start the local cluster (`macb up`'s, and `macb reproduce`'s when no API answers)
    and wait for every service and the API; stop every process on the way out, however
    that is. SIGTERM and Ctrl-C only set `stop` from here on. Raises ClusterDidNotStart.
    With a signal during start-up it yields at once, `stop` set (and `api` maybe None)."""
    from shared.net.bus import Bus

    if slots < 1:
        raise ValueError(f"--slots must be at least 1, not {slots}")
    plan = cluster_plan(
        actors,
        endpoint,
        str(data_dir),
        api=api_addr,
        slots=slots,
        secrets=secrets,
        group_size=group_size,
    )
    if secrets:  # every service's files, before any process starts (SecurityError: exit 2)
        from shared.net.security import Security

        for spec in plan:
            sec = Security.from_env({**os.environ, **dict(spec.env)})
            sec.for_router().check("router") if spec.name == "router" else sec.check("client")
    try:  # before any process starts: a port taken is another cluster's (or anyone's)
        check_ports(plan)
    except PortInUse as err:
        print(f"cannot start the local cluster: {err}", file=sys.stderr)
        raise ClusterDidNotStart("ports", code=2) from None
    cluster = Cluster(plan, data_dir / "logs", echo=echo)
    stop = _stop_on_signals()
    api = None
    try:
        try:
            _start_cluster(cluster, data_dir)
        except (PortInUse, DidNotListen, TimeoutError) as err:
            print(f"the cluster did not start: {err}", file=sys.stderr)
            raise ClusterDidNotStart("router") from None
        with Bus([endpoint]) as bus:
            if not _services_came_up(bus, cluster, stop):
                raise ClusterDidNotStart("services")
            if api_addr is not None and not stop.is_set():
                api = _api_client_at(api_addr)
                if not _api_came_up(api, cluster, data_dir):
                    raise ClusterDidNotStart("api")
            yield LocalCluster(cluster, bus, api, stop)
    finally:
        if api is not None:
            api.close()
        cluster.stop()
        print("cluster stopped", file=sys.stderr)


def _run_flags(args: argparse.Namespace) -> list[str]:
    """The flags given that only --run takes: its seeds, folder and config's values."""
    return ["--seeds"] * bool(args.seeds) + ["--out"] * bool(args.out) + given_config_flags(args)


def _up_experiment(args: argparse.Namespace) -> tuple[TrainConfig | None, dict | None]:
    """`--run CONFIG` as a config (for the bus) and an experiment body (for the API);
    (None, None) without --run. Raises ConfigError or OSError."""
    if not args.run:
        return None, None
    cfg, note = one_run_config(args.run, config_overrides(args))
    check_actors(cfg, args.actors)
    if note and args.no_api:
        print(f"note: {note}", file=sys.stderr)
    body = experiment_body(
        argparse.Namespace(**{**vars(args), "config": args.run, "grid": None, "name": None})
    )
    return cfg, body


def _stop_on_signals() -> threading.Event:
    """SIGTERM and Ctrl-C only set this event: the main loop then stops the children."""
    import signal

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def _start_cluster(cluster: Cluster, data_dir: Path) -> None:
    cluster.start()
    print(
        f"cluster up: {', '.join(s.name for s in cluster.plan)}; logs in {data_dir}/logs",
        file=sys.stderr,
    )


def _services_came_up(bus: Bus, cluster: Cluster, stop: threading.Event) -> bool:
    """Wait up to 60 s for every service but the router (which does not announce itself)
    to answer; False if that fails or one dies. A signal ends the wait early with True."""
    from shared.net.control import discover

    deadline = time.monotonic() + 60
    while len(discover(bus)) < len(cluster.plan) - 1 and not stop.is_set():
        if time.monotonic() > deadline or cluster.dead():
            print(f"services did not come up (dead: {cluster.dead()})", file=sys.stderr)
            return False
        time.sleep(0.2)
    return True


def _api_client_at(api_addr: str) -> ApiClient:
    from services.api.client import ApiClient

    return ApiClient(f"http://{api_addr}")


def _api_came_up(api: ApiClient, cluster: Cluster, data_dir: Path) -> bool:
    """Wait up to 60 s for the API to answer (giving up early if a service dies). An
    answer counts only while our API process lives: one that failed to bind is not
    stood in for by whatever else answers on its port."""
    try:
        api.wait_healthy(60, alive=lambda: not cluster.dead())
    except TimeoutError as err:
        print(f"{err} (dead: {cluster.dead()})", file=sys.stderr)
        return False
    print(
        f"dashboard: {api.url}/   API docs: {api.url}/docs   store: {data_dir}/api.sqlite3",
        file=sys.stderr,
    )
    return True


def _experiment(
    args: argparse.Namespace,
    cfg: TrainConfig,
    body: dict,
    bus: Bus,
    api: ApiClient | None,
    data_dir: Path,
) -> Callable[[], int]:
    """The `--run` experiment as a call returning its exit code: through the API when
    there is one (the run is then stored and shown), else straight on the bus."""
    out = Path(args.out) if args.out else None
    if api is not None:
        return lambda: run_via_api(api, body, out, args.quiet, data_dir)
    return lambda: follow_run(bus, cfg, args.actors, out, args.quiet)


def _run_while_cluster_lives(
    work: Callable[[], int], cluster: Cluster, stop: threading.Event
) -> int:
    """Run `work` in a thread, restarting services that die, so that a signal or a
    service that keeps dying ends the wait (and then `macb up` stops the cluster); its
    exit code, or 1 if it did not finish."""
    result: list[int] = []
    runner = threading.Thread(target=lambda: result.append(work()), daemon=True)
    runner.start()
    while runner.is_alive() and not stop.is_set():
        runner.join(0.2)
        if (gone := cluster.supervise()) is not None:
            print(f"{gone} keeps dying: stopping the cluster", file=sys.stderr)
            stop.set()
    return result[0] if result else 1


def _print_where_results_stay(api: ApiClient, data_dir: Path) -> None:
    print(
        f"the dashboard was at {api.url}/ ; the experiment and every metric "
        f"point are kept in {data_dir}/api.sqlite3: "
        f"`macb up --data-dir {data_dir}` shows them again",
        file=sys.stderr,
    )


def _serve_until_stopped(cluster: Cluster, stop: threading.Event, quiet: bool = False) -> int:
    """No --run: keep the cluster up, restarting services that die, until a signal (0)
    or until one keeps dying (1)."""
    if not quiet:
        print(
            "waiting for runs (macb run CONFIG, or macb start CONFIG on the bus); "
            "Ctrl-C stops the cluster",
            file=sys.stderr,
        )
    while not stop.wait(0.5):
        if (gone := cluster.supervise()) is not None:
            print(f"{gone} keeps dying: stopping the cluster", file=sys.stderr)
            return 1
    return 0
