"""The `macb` parser: every config key is a flag on each command that takes a config,
and flag values reach the config the way the schema wants them.

The flags are built from `TrainConfig`, so these tests pin the contract rather than a
list: a new field must show up everywhere with the same dest, and its default given as
a flag must come back as that default.
"""

from __future__ import annotations

import argparse
import importlib
import os
from types import ModuleType

import pytest

from shared.config import TrainConfig, make_config

CONFIG_COMMANDS = ("train", "start", "run", "up")
POSITIONALS = {"run": ["c.yaml"]}  # what a command needs before its flags parse


def _import(name: str) -> ModuleType:
    """Import a cli module without keeping the thread variables `cli` sets on import:
    later tests' child processes should see the environment they always did."""
    saved = dict(os.environ)
    try:
        return importlib.import_module(name)
    finally:
        os.environ.clear()
        os.environ.update(saved)


@pytest.fixture(scope="module")
def subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = _import("cli.main").build_parser()
    (sub,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _parse(subparsers, command: str, *flags: str) -> argparse.Namespace:
    return subparsers[command].parse_args([*POSITIONALS.get(command, []), *flags])


def test_commands_and_their_order(subparsers):
    assert list(subparsers) == ["train", "serve", "start", "stop", "run", "ls", "plot", "ps", "up"]


def test_every_config_field_is_a_flag_with_the_same_dest_on_every_config_command(subparsers):
    flags = _import("cli.config_flags")
    for command, p in subparsers.items():
        actions = {a.dest: a for a in p._actions if a.dest.startswith("cfg_")}
        if command not in CONFIG_COMMANDS:
            assert actions == {}, command
            continue
        assert list(actions) == [f"cfg_{name}" for name in TrainConfig.model_fields], command
        for name, field in TrainConfig.model_fields.items():
            a = actions[f"cfg_{name}"]
            assert a.option_strings == [f"--{name.replace('_', '-')}"], (command, name)
            assert a.dest == flags.flag_dest(name) and a.metavar == name.upper()
            assert a.default is None, "a flag not given must not override the file"
            assert (field.description or "") in a.help and "(default: " in a.help


def _as_flag(name: str, value: object) -> str:
    if isinstance(value, tuple):
        return ",".join(map(str, value))
    return str(value)


@pytest.mark.parametrize("command", CONFIG_COMMANDS)
def test_each_default_given_as_a_flag_comes_back_as_that_default(subparsers, command):
    flags = _import("cli.config_flags")
    defaults = TrainConfig().model_dump()
    argv = [f"--{n.replace('_', '-')}={_as_flag(n, v)}" for n, v in defaults.items()]
    overrides = flags.config_overrides(_parse(subparsers, command, *argv))
    assert set(overrides) == set(defaults)
    assert make_config(overrides).model_dump() == defaults


def test_string_values_stay_strings_and_the_rest_is_read_as_yaml(subparsers):
    flags = _import("cli.config_flags")
    args = _parse(
        subparsers,
        "train",
        *("--explore", "none", "--hash", "none", "--learner-impl", "reference"),
        *("--hidden", "64, 32,", "--beta", "0.1", "--k", "64", "--learner-lanes", "2"),
        *("--time-limit-terminal", "yes"),
    )
    assert flags.config_overrides(args) == {
        "explore": "none",
        "hash": "none",
        "learner_impl": "reference",
        "hidden": ["64", "32"],
        "beta": 0.1,
        "k": 64,
        "learner_lanes": 2,
        "time_limit_terminal": True,
    }
    assert {"task", "algo", "explore", "hash", "key", "reward"} <= flags.STRING_FIELDS
    assert "learner_lanes" not in flags.STRING_FIELDS, "'auto' or a number"
    assert flags.config_overrides(_parse(subparsers, "up")) == {}
