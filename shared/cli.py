"""The `macb` command. Subcommands are small wrappers over library functions."""

from __future__ import annotations

import argparse
import logging
import sys
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

    module = importlib.import_module(f"services.{args.role}.main")
    service_id = args.id or f"{args.role}-{socket.gethostname()}-{os.getpid()}"
    connect = args.connect or default_connect()
    service = module.make_service(service_id, connect, Path(args.data_dir))
    service.install_signal_handlers()
    service.serve_forever()
    return 0


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
    return parser


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
