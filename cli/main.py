"""`macb`: the parser assembled from the command groups, and the entry point.

Each group module (cli.train, cli.cluster, cli.api, cli.export, cli.reproduce) adds its own
subcommands; this module only fixes their order in `macb --help`, sets up logging and, in a
process `macb up` started, arms its death with `macb up` (`shared.procs.die_with_env_parent`).
"""

from __future__ import annotations

import argparse
import gc
import logging
import sys
from collections.abc import Callable

from pydantic import ValidationError

from cli import api, cluster, export, reproduce, results, security, train, view
from cli.config_flags import HelpFormatter
from shared import procs
from shared.config import error_text
from shared.net.security import BusError, SecurityError

# In the order `macb --help` lists them.
COMMANDS: tuple[Callable[[argparse._SubParsersAction], None], ...] = (
    train.add_train_parser,
    cluster.add_serve_parser,
    cluster.add_start_parser,
    api.add_stop_parser,
    api.add_run_parser,
    api.add_ls_parser,
    api.add_plot_parser,
    export.add_export_parser,
    cluster.add_ps_parser,
    cluster.add_up_parser,
    reproduce.add_reproduce_parser,
    results.add_results_parser,
    view.add_view_parser,
    security.add_certs_parser,
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="macb",
        description="Multi-agent count-based exploration (MACB): train DDPG / MADDPG agents "
        "with SimHash count bonuses on sparse particle tasks.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for add_parser in COMMANDS:
        add_parser(sub)
    for command in sub.choices.values():  # every command's --help says its defaults
        if command.formatter_class is argparse.HelpFormatter:
            command.formatter_class = HelpFormatter
    return parser


#: Options whose value is itself a command line: argparse takes a value starting with '-'
#: for an option of its own ("expected one argument"), so `--sbatch-args '--mem=4G'` is
#: given to it as `--sbatch-args=--mem=4G`, which it reads as the value.
LINE_VALUED = ("--sbatch-args",)


def join_line_values(argv: list[str]) -> list[str]:
    """`argv` with each LINE_VALUED option and the word after it made one `OPT=VALUE`
    (up to a `--`, after which nothing is an option)."""
    out: list[str] = []
    words = iter(argv)
    for word in words:
        if word == "--":
            out += [word, *words]
            break
        if word in LINE_VALUED:
            value = next(words, None)
            out.append(word if value is None else f"{word}={value}")
        else:
            out.append(word)
    return out


def main(argv: list[str] | None = None) -> int:
    try:  # a service of `macb up` dies with it, however it ends (SIGKILL included)
        procs.die_with_env_parent()
    except ValueError as err:
        print(f"macb: {err}", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)  # not a line per API call
    args = build_parser().parse_args(join_line_values(sys.argv[1:] if argv is None else argv))
    security.apply_security_flags(args)
    try:
        return args.func(args)
    # A bus setting or file that cannot be used, or a session that cannot open (no router
    # at the endpoints, a port taken): said in one line, as any other bad input.
    except (SecurityError, BusError) as err:
        print(f"macb {args.command}: {err}", file=sys.stderr)
        return 2
    # A value a command hands a model (the API's settings, a figure's body) that the
    # model refuses: the field and the reason, not pydantic's dump.
    except ValidationError as err:
        print(f"macb {args.command}: {error_text(err)}", file=sys.stderr)
        return 2


def entry() -> int:
    """The `macb` command (and `python -m cli`): `main`, then a lighter interpreter exit.

    With torch loaded, Python's own teardown runs the cyclic collector over every object
    torch made, again and again as it clears the modules: most of a service's stop. One
    collection here runs every finalizer of the garbage there is (so nothing a finalizer
    would flush is lost), and freezing the survivors keeps the teardown from walking them
    again; files are closed by the commands themselves. Not in `main`, which tests call in
    their own process, where a freeze would outlive the call.
    """
    code = main()
    if "torch" in sys.modules:
        gc.collect()
        gc.freeze()
    return code
