"""The config flags: one per `TrainConfig` field, on every command that takes a config.

`train`, `start`, `run` and `up` accept the keys of a config file as flags that override
the file. Names, help and how a value is read all come from the schema, so a new field
gets its flag without touching the CLI; the exceptions are listed below, each with why.
"""

from __future__ import annotations

import argparse
from typing import Any, Literal, get_args, get_origin

import yaml

from shared.config import ConfigError, TrainConfig, make_config, read_config_file

# Exception: these tuple fields take a comma list (`--hidden 400,300`) rather than YAML,
# and show their default that way; YAML would read "400,300" as one string.
COMMA_LIST_FIELDS = frozenset({"hidden"})


def _takes_only_strings(annotation: Any) -> bool:
    """A `str` or a Literal of strings only: its flag value is kept as typed, never read
    as YAML, so `--explore none` stays "none" and does not become null."""
    if annotation is str:
        return True
    if get_origin(annotation) is not Literal:
        return False
    return all(isinstance(v, str) for v in get_args(annotation))


STRING_FIELDS = frozenset(
    name for name, f in TrainConfig.model_fields.items() if _takes_only_strings(f.annotation)
)


def at_least_one(text: str) -> int:
    """An argparse type: a whole number >= 1 (`--actors`, ...), refused by argparse
    (exit 2, naming the flag) otherwise."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value}: at least 1")
    return value


def flag_name(field: str) -> str:
    """The option string of a field: underscores become dashes."""
    return f"--{field.replace('_', '-')}"


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Defaults in --help, except where there is nothing to say: no value (None), an
    off switch (False), or a help text that states its default itself (config keys)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default in (None, False) or "(default:" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


def flag_dest(field: str) -> str:
    """The attribute a field's flag sets; prefixed so no command's own flag can clash."""
    return f"cfg_{field}"


def add_config_flags(p: argparse.ArgumentParser, source: str = "--config") -> None:
    """One flag per config key; each overrides the file (`source`: how the command names
    it, for the help's heading). Values stay raw strings here (`config_overrides` reads
    them) so that a flag not given is told apart by None."""
    group = p.add_argument_group(f"config keys (override {source})")
    for name, field in TrainConfig.model_fields.items():
        default = field.default
        if name in COMMA_LIST_FIELDS:
            default = ",".join(map(str, default))
        group.add_argument(
            flag_name(name),
            dest=flag_dest(name),
            metavar=name.upper(),
            default=None,
            help=f"{field.description or ''} (default: {default})".strip(),
        )


def read_flag_value(name: str, raw: str) -> Any:
    """A flag's raw text as the value its field takes (validation is the schema's job)."""
    if name in COMMA_LIST_FIELDS:
        return [s.strip() for s in raw.split(",") if s.strip()]
    if name in STRING_FIELDS:
        return raw
    try:
        return yaml.safe_load(raw)
    except yaml.YAMLError as err:
        problem = getattr(err, "problem", None) or "not YAML"
        raise ConfigError(f"{flag_name(name)} {raw!r}: not a value ({problem})") from None


def given_config_flags(args: argparse.Namespace) -> list[str]:
    """The config fields' flags given (their values not read), in field name order."""
    return [
        flag_name(n)
        for n in sorted(TrainConfig.model_fields)
        if getattr(args, flag_dest(n)) is not None
    ]


def config_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The config keys given as flags, each read the way its field wants."""
    out: dict[str, Any] = {}
    for name in TrainConfig.model_fields:
        raw = getattr(args, flag_dest(name))
        if raw is not None:
            out[name] = read_flag_value(name, raw)
    return out


def one_run_config(path: str, overrides: dict[str, Any]) -> tuple[TrainConfig, str | None]:
    """A config file as ONE run (`macb train`, `start`, `up --no-api`), flags over it,
    and a note to show, if any. The shipped configs list the thesis's 3 `seeds` for
    `macb run`; one run takes the first (or `--seed`), and the note says so. The other
    experiment keys have no one-run meaning: a grid or arms is refused, naming `macb run`.
    Raises ConfigError or OSError."""
    data = read_config_file(path)
    note = None
    for key in ("grid", "arms"):
        if key in data:
            raise ConfigError(
                f"{key}: {path} is an experiment of several runs; this command runs one "
                f"config: `macb run {path}` runs them all"
            )
    if "seeds" in data:
        seeds = data.pop("seeds")
        if "seed" in data:
            raise ConfigError(f"seeds: {path} gives seed and seeds; give one of them")
        if not isinstance(seeds, list) or not seeds:
            raise ConfigError(f"seeds: {path}: a non-empty list of seeds, like [0, 1, 2]")
        data["seed"] = seeds[0]
        if "seed" not in overrides and len(seeds) > 1:
            note = (
                f"{path} lists seeds {seeds}: this runs one run, seed {seeds[0]} (--seed "
                f"picks another; `macb run {path}` runs every seed)"
            )
    return make_config({**data, **overrides}), note


def resolve_config(args: argparse.Namespace) -> TrainConfig:
    """`--config FILE` (if given) with the flags over it, as one run (a note on stderr if
    the file lists several seeds); raises ConfigError or OSError."""
    import sys

    overrides = config_overrides(args)
    if not args.config:
        return make_config(overrides)
    cfg, note = one_run_config(args.config, overrides)
    if note and not getattr(args, "seeds", None):  # (`train --seeds` says its own seeds)
        print(f"note: {note}", file=sys.stderr)
    return cfg
