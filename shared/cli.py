"""The `macb` command. Subcommands are small wrappers over library functions."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import Any

import yaml

from shared.config import ConfigError, TrainConfig, load_config, make_config


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


SERVICES = ("router", "counter", "learner", "actor", "evaluator")


def cmd_serve(args: argparse.Namespace) -> int:
    """Run one service in the foreground until SIGTERM / Ctrl-C."""
    import os
    import socket

    from shared.bus import DEFAULT_ENDPOINT, default_connect

    if args.role == "router":
        from services.router.main import serve

        serve(args.listen or [os.environ.get("MACB_ZENOH_LISTEN", DEFAULT_ENDPOINT)])
        return 0
    import importlib

    modules = {"evaluator": "services.actor.evaluator"}
    module = importlib.import_module(modules.get(args.role, f"services.{args.role}.main"))
    service_id = args.id or f"{args.role}-{socket.gethostname()}-{os.getpid()}"
    connect = args.connect or default_connect()
    service = module.make_service(service_id, connect, Path(args.data_dir))
    service.install_signal_handlers()
    service.serve_forever()
    return 0


DISTRIBUTED_FIELDS = ("replay_ratio", "policy_lag", "policy_version")


def follow_run(bus, cfg: TrainConfig, actors: int, out: Path | None, quiet: bool) -> int:
    """Start a run on the cluster, follow it to the end, write its metrics; exit code."""
    import json

    from tqdm import tqdm

    from shared.control import NoFreeServices, send_stop, start_run
    from shared.trainer import METRIC_FIELDS, MetricsWriter

    writer = None
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "config.json").write_text(json.dumps(cfg.model_dump(mode="json"), indent=2) + "\n")
        writer = MetricsWriter(out, METRIC_FIELDS + DISTRIBUTED_FIELDS)
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
    from shared.bus import Bus, default_connect
    from shared.control import send_stop

    with Bus(args.connect or default_connect()) as bus:
        send_stop(bus, args.run)
    print(f"sent stop for run {args.run}")
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

    cfg = None
    if args.run:
        try:
            cfg = load_config(args.run, _overrides(args))
        except (ConfigError, OSError) as err:
            print(f"macb up: invalid config: {err}", file=sys.stderr)
            return 2
    data_dir = Path(args.data_dir)
    plan = cluster_plan(args.actors, args.endpoint, str(data_dir))
    cluster = Cluster(plan, data_dir / "logs", echo=not args.quiet_services)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    code = 0
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
            if cfg is not None and not stop.is_set():
                out = Path(args.out) if args.out else None
                runner = threading.Thread(
                    target=lambda: setattr(
                        runner, "code", follow_run(bus, cfg, args.actors, out, args.quiet)
                    ),
                    daemon=True,
                )
                runner.start()
                while runner.is_alive() and not stop.is_set():
                    runner.join(0.2)
                    if cluster.dead():
                        print(f"service(s) died: {cluster.dead()}", file=sys.stderr)
                        stop.set()
                code = getattr(runner, "code", 1)
            else:
                print(
                    "waiting for runs (macb start CONFIG); Ctrl-C stops the cluster",
                    file=sys.stderr,
                )
                while not stop.wait(0.5):
                    if cluster.dead():
                        print(f"service(s) died: {cluster.dead()}", file=sys.stderr)
                        code = 1
                        break
    finally:
        cluster.stop()
        print("cluster stopped", file=sys.stderr)
    return code


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
        help="run one service of the cluster (router, counter, learner, actor, evaluator)",
        description="Run one service in the foreground. Services connect as Zenoh clients to "
        "the router (MACB_ZENOH_CONNECT or --connect, default tcp/127.0.0.1:7447), announce "
        "themselves with a liveliness token and wait for runs on macb/control/start.",
    )
    s.add_argument("role", choices=SERVICES)
    s.add_argument("--id", help="service id (default: role-host-pid); actors need distinct ids")
    s.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint(s)")
    s.add_argument("--listen", action="append", metavar="ENDPOINT", help="router only: listen on")
    s.add_argument("--data-dir", default="data", help="where snapshots and checkpoints go")
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

    sp = sub.add_parser("stop", help="stop a run")
    sp.add_argument("run", help="run id")
    sp.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint")
    sp.set_defaults(func=cmd_stop)

    ps = sub.add_parser("ps", help="list live services and the runs they serve")
    ps.add_argument("--connect", action="append", metavar="ENDPOINT", help="router endpoint")
    ps.set_defaults(func=cmd_ps)

    up = sub.add_parser(
        "up",
        help="start the local cluster (router, counter, learner, evaluator, actors)",
        description="Start every service as a local process with the same commands "
        "docker-compose.yml runs. With --run CONFIG, run that experiment on it and stop; "
        "otherwise serve until Ctrl-C / SIGTERM. No process outlives this command.",
    )
    up.add_argument("--actors", type=int, default=1, help="actor processes")
    up.add_argument("--endpoint", default="tcp/127.0.0.1:7447", help="router endpoint")
    up.add_argument("--data-dir", default="data", help="snapshots, checkpoints, logs")
    up.add_argument("--run", metavar="CONFIG", help="run this experiment, then stop")
    up.add_argument("--out", metavar="DIR", help="with --run: write metrics here")
    up.add_argument("--quiet", action="store_true", help="no progress bar")
    up.add_argument("--quiet-services", action="store_true", help="service logs to files only")
    _add_config_flags(up)
    up.set_defaults(func=cmd_up)
    return parser


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
