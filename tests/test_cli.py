"""The `macb` parser: every config key is a flag on each command that takes a config,
and flag values reach the config the way the schema wants them.

The flags are built from `TrainConfig`, so these tests pin the contract rather than a
list: a new field must show up everywhere with the same dest, and its default given as
a flag must come back as that default.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

from shared.config import ConfigError, TrainConfig, make_config
from tests.conftest import ROOT
from tests.harness import free_port, macb, wait_for

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
    assert list(subparsers) == [
        *("train", "serve", "start", "stop", "run", "ls", "plot", "export", "ps", "up"),
        *("reproduce", "results", "view", "certs"),
    ]


def test_help_states_each_default_once_and_only_where_there_is_one(subparsers):
    for command in ("train", "reproduce"):
        text = " ".join(subparsers[command].format_help().split())
        assert "(default: runs/train)" in text or command != "train"
        assert text.count("(default:") == len(re.findall(r"\(default: [^)]*\)", text))
        assert not re.search(r"\(default: [^)]*\) \(default:", text), command  # twice
        assert "--quiet no progress bar (default" not in text  # an off switch: nothing
    train = " ".join(subparsers["train"].format_help().split())
    assert "(default: 0.8)" in train and "(default: 60.0)" in train  # beta, --cut-every


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
    if value is None:
        return "null"  # an optional field's "not set", as YAML writes it
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


# ---------------------------------------------------------------- macb run: grid and arms
def _body(subparsers, tmp_path, config: str, *flags: str) -> dict:
    path = tmp_path / "c.yaml"
    path.write_text(config)
    api = _import("cli.api")
    return api.experiment_body(subparsers["run"].parse_args([str(path), *flags]))


BASE_YAML = "task: speaker_listener\nalgo: cen-maddpg\nk: 64\n"


def test_grid_flags_take_any_config_key_and_read_values_like_its_flag(subparsers, tmp_path):
    body = _body(
        subparsers,
        tmp_path,
        BASE_YAML,
        *("--grid", "explore=none,dis-macb,cen-macb", "--grid", "beta=0.2,0.8"),
        *("--grid", "hidden=[64,64],[32]", "--grid", "time-limit-terminal=true,false"),
        *("--grid", "learner_lanes=auto,2", "--grid", "task=on, off", "--seeds", "0", "1", "2"),
    )
    assert body["grid"] == {
        "explore": ["none", "dis-macb", "cen-macb"],
        "beta": [0.2, 0.8],
        "hidden": [[64, 64], [32]],
        "time_limit_terminal": [True, False],
        "learner_lanes": ["auto", 2],
        "task": ["on", "off"],  # a string field's values stay strings (YAML: booleans)
    }
    assert body["seeds"] == [0, 1, 2] and body["k"] == 64 and "arms" not in body


def test_grid_flags_merge_over_the_files_grid(subparsers, tmp_path):
    config = BASE_YAML + "grid: {beta: [0.1], k: [32, 64]}\n"
    body = _body(subparsers, tmp_path, config, "--grid", "beta=0.2,0.4")
    assert body["grid"] == {"beta": [0.2, 0.4], "k": [32, 64]}


@pytest.mark.parametrize(
    "item, says",
    [
        ("seed=0,1", "use --seeds"),
        ("seeds=0,1", "use --seeds"),
        ("gama=0.9", "'gama' is not a config key"),
        ("beta=", "no values"),
        ("beta", "no values"),
        ("hidden=64,32", "as a list"),
    ],
)
def test_bad_grid_flags_are_refused_before_the_api_is_asked(subparsers, tmp_path, item, says):
    with pytest.raises(ConfigError, match=re.escape(says)):
        _body(subparsers, tmp_path, BASE_YAML, "--grid", item)


def test_a_grid_key_given_twice_is_refused(subparsers, tmp_path):
    with pytest.raises(ConfigError, match="given twice"):
        _body(subparsers, tmp_path, BASE_YAML, "--grid", "beta=0.1", "--grid", "beta=0.2")


def test_arms_file_is_sent_as_the_arms_list(subparsers, tmp_path):
    arms = tmp_path / "arms.yaml"
    arms.write_text(
        "- {name: no bonus, explore: none}\n- {name: cen-macb, explore: cen-macb}\n"
        "- name: control\n  explore: constant\n  beta: 0.5\n"
    )
    body = _body(subparsers, tmp_path, BASE_YAML, "--arms", str(arms), "--grid", "k=32,64")
    assert body["arms"] == [
        {"name": "no bonus", "explore": "none"},
        {"name": "cen-macb", "explore": "cen-macb"},
        {"name": "control", "explore": "constant", "beta": 0.5},
    ]
    assert body["grid"] == {"k": [32, 64]}
    arms.write_text("arms:\n  - {name: a}\n")  # a mapping holding the list works too
    assert _body(subparsers, tmp_path, BASE_YAML, "--arms", str(arms))["arms"] == [{"name": "a"}]
    for bad in ("- {explore: none}\n", "name: a\n", "[]\n", "- [1, 2]\n", "- {name: [x\n"):
        arms.write_text(bad)
        with pytest.raises(ConfigError, match="arm|YAML"):
            _body(subparsers, tmp_path, BASE_YAML, "--arms", str(arms))


def test_with_arms_the_base_alone_may_break_a_cross_field_rule_but_not_a_field(
    subparsers, tmp_path
):
    arms = tmp_path / "arms.yaml"
    arms.write_text("- {name: ddpg, algo: ddpg}\n")
    simple = "task: simple\n"  # with the default algo (cen-maddpg) this alone is invalid
    body = _body(subparsers, tmp_path, simple, "--arms", str(arms))
    assert body["task"] == "simple" and body["arms"] == [{"name": "ddpg", "algo": "ddpg"}]
    body = _body(subparsers, tmp_path, simple, "--grid", "algo=ddpg")
    assert body["grid"] == {"algo": ["ddpg"]}
    with pytest.raises(ConfigError, match="config: algo cen-maddpg needs several agents"):
        _body(subparsers, tmp_path, simple)
    with pytest.raises(ConfigError, match="beta: Input should be less than or equal to 100"):
        _body(subparsers, tmp_path, simple, "--arms", str(arms), "--beta", "1000")


def test_macb_run_refuses_a_bad_grid_with_exit_2_without_an_api(tmp_path):
    config = tmp_path / "c.yaml"
    config.write_text(BASE_YAML)
    proc = macb("run", str(config), "--grid", "seed=1,2", "--api", "http://127.0.0.1:1")
    assert proc.returncode == 2, proc.stderr
    assert "the seed is not a grid key: use --seeds" in proc.stderr


# ---------------------------------------------------------------- seeds in config files
SHIPPED = ROOT / "configs" / "fig8" / "sparse-cen-macb.yaml"


def test_one_run_of_a_file_listing_seeds_takes_the_first_and_says_so():
    flags = _import("cli.config_flags")
    cfg, note = flags.one_run_config(str(SHIPPED), {})
    assert cfg.seed == 0 and cfg.explore == "cen-macb" and cfg.k == 512
    assert f"{SHIPPED} lists seeds [0, 1, 2]: this runs one run, seed 0" in note
    assert f"`macb run {SHIPPED}` runs every seed" in note
    cfg, note = flags.one_run_config(str(SHIPPED), {"seed": 2})
    assert cfg.seed == 2 and note is None, "--seed picks another, without a note"


@pytest.mark.parametrize(
    "text, says",
    [
        ("seed: 1\nseeds: [0, 1]\n", "gives seed and seeds"),
        ("seeds: []\n", "a non-empty list of seeds"),
        ("seeds: 3\n", "a non-empty list of seeds"),
        ("grid: {beta: [0.1, 0.2]}\n", "grid: .* is an experiment of several runs"),
        ("arms: [{name: a}]\n", "arms: .*`macb run .*` runs them all"),
    ],
)
def test_one_run_refuses_what_only_an_experiment_has(tmp_path, text, says):
    flags = _import("cli.config_flags")
    path = tmp_path / "c.yaml"
    path.write_text(BASE_YAML + text)
    with pytest.raises(ConfigError, match=says):
        flags.one_run_config(str(path), {})


def test_macb_run_sends_the_files_seeds_unless_a_flag_says_otherwise(subparsers, tmp_path):
    listed = BASE_YAML + "seeds: [0, 1, 2]\n"
    assert _body(subparsers, tmp_path, listed)["seeds"] == [0, 1, 2]
    assert _body(subparsers, tmp_path, listed, "--seeds", "4", "5")["seeds"] == [4, 5]
    one = _body(subparsers, tmp_path, listed, "--seed", "5")
    assert one["seed"] == 5 and "seeds" not in one


def test_macb_train_runs_one_seed_of_a_shipped_config(tmp_path):
    out = tmp_path / "out"
    proc = macb(
        *["train", "--config", "configs/fig3/beta0.8.yaml", "--episodes", "2"],
        *["--eval-every", "2", "--eval-episodes", "1", "--hidden", "16"],
        *["--learning-starts", "10", "--out", str(out), "--quiet"],
    )
    assert proc.returncode == 0, proc.stderr
    assert "lists seeds [0, 1, 2]: this runs one run, seed 0" in proc.stderr
    config = json.loads((out / "config.json").read_text())
    assert config["seed"] == 0 and config["beta"] == 0.8 and config["episodes"] == 2


@pytest.mark.parametrize("command", ["start", "up"])
def test_a_lockstep_run_with_several_actors_is_refused_before_anything_starts(tmp_path, command):
    """`profile: thesis` runs the thesis's loop in the cluster, which has one actor."""
    config = tmp_path / "c.yaml"
    config.write_text("task: simple\nalgo: ddpg\nprofile: thesis\n")
    flag = ["--config", str(config)] if command == "start" else ["--run", str(config)]
    connect = "--endpoint" if command == "up" else "--connect"
    proc = macb(command, *flag, "--actors", "2", connect, "tcp/127.0.0.1:1")
    assert proc.returncode == 2, proc.stderr
    assert "actors: interleave lockstep" in proc.stderr, proc.stderr


# ---------------------------------------------------------------- the data dir
RULE = "(default: $XDG_STATE_HOME/macb, else ~/.local/state/macb; here "


def test_the_default_data_dir_is_the_users_state_dir_and_help_says_so(
    subparsers, monkeypatch, tmp_path
):
    """Not `data` in whatever folder the command runs in (a checkout got an untracked
    data/): $XDG_STATE_HOME/macb, else ~/.local/state/macb (a relative
    XDG_STATE_HOME is ignored, as the XDG spec says)."""
    files = _import("shared.persist.files")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    assert files.default_data_dir() == tmp_path / "state" / "macb"
    monkeypatch.setenv("XDG_STATE_HOME", "state")
    assert files.default_data_dir() == tmp_path / "home" / ".local" / "state" / "macb"
    monkeypatch.delenv("XDG_STATE_HOME")
    assert files.default_data_dir() == tmp_path / "home" / ".local" / "state" / "macb"
    for command, positional in [("serve", ["api"]), ("up", []), ("reproduce", ["fig3"])]:
        parser = subparsers[command]
        assert parser.parse_args(positional).data_dir is None, command
        assert RULE in " ".join(parser.format_help().split()), command


@pytest.mark.parametrize("given", [None, "elsewhere"])
def test_up_and_reproduce_start_their_cluster_in_that_data_dir(
    subparsers, monkeypatch, tmp_path, given
):
    cluster = _import("cli.cluster")
    state = tmp_path / "state"
    monkeypatch.setenv("XDG_STATE_HOME", str(state))
    started = []

    @contextlib.contextmanager
    def no_cluster(actors, endpoint, data_dir, *args, **kw):
        started.append(Path(data_dir))
        raise cluster.ClusterDidNotStart("not in this test")
        yield

    monkeypatch.setattr(cluster, "local_cluster", no_cluster)
    flag = ["--data-dir", str(tmp_path / given)] if given else []
    up = subparsers["up"].parse_args(flag)
    assert up.func(up) == 1
    api = ["--api", f"http://127.0.0.1:{free_port()}", "--out", str(tmp_path / "out")]
    reproduce = subparsers["reproduce"].parse_args(["fig3", *api, *flag])
    assert reproduce.func(reproduce) == 1
    assert started == [tmp_path / given if given else state / "macb"] * 2


@pytest.mark.parametrize("env", [{}, {"MACB_API_DATA_DIR": "from-env"}])
def test_serve_api_run_in_a_checkout_leaves_it_clean(tmp_path, env):
    """`macb serve api` without --data-dir: its store in the per-user dir, or where
    MACB_API_DATA_DIR says; nothing in the folder it runs in."""
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    env = {k: str(tmp_path / v) for k, v in env.items()}
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "cli", "serve", "api", "--listen-http", f"127.0.0.1:{port}"]
        + ["--connect", "tcp/127.0.0.1:1"],
        cwd=checkout,
        env={**os.environ, "PYTHONPATH": str(ROOT), "XDG_STATE_HOME": str(tmp_path), **env},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        wait_for(lambda: _health(port), timeout=60, what="the API answering")
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=30)
    store = Path(env.get("MACB_API_DATA_DIR", tmp_path / "macb")) / "api.sqlite3"
    assert store.exists(), out
    assert f"store {store}" in out
    assert list(checkout.iterdir()) == []


def _health(port: int) -> bool:
    import httpx

    try:
        return httpx.get(f"http://127.0.0.1:{port}/health", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


@pytest.mark.parametrize("command", CONFIG_COMMANDS)
def test_the_config_keys_heading_names_how_the_command_takes_its_file(subparsers, command):
    """The config flags' heading in --help says what they override: the command's own
    flag or argument for the config file (`macb up` has --run CONFIG, `macb run` a
    positional CONFIG; neither has --config)."""
    p = subparsers[command]
    (title,) = [g.title for g in p._action_groups if (g.title or "").startswith("config keys")]
    named = re.fullmatch(r"config keys \(override (.+)\)", title).group(1)
    flag, _, metavar = named.partition(" ")
    ours = {s: a for a in p._actions for s in a.option_strings}
    if flag.startswith("--"):
        assert flag in ours, f"macb {command}: the heading names {flag}, not a flag of it"
        assert not metavar or ours[flag].metavar == metavar
    else:
        assert flag in [a.metavar for a in p._actions if not a.option_strings], title


def test_the_command_freezes_the_heap_before_a_torch_process_exits():
    """`entry` (the `macb` script, `python -m cli`): with torch loaded, one collection
    and a gc freeze, so the interpreter's teardown does not walk torch's objects again;
    without torch, nothing (`main` itself, which tests call in-process, never freezes)."""
    code = (
        "import gc, sys\n"
        "import cli.main as m\n"
        "{torch}"
        "sys.argv = ['macb', 'results', '--check']\n"
        "m.main(sys.argv[1:]); after_main = gc.get_freeze_count()\n"
        "m.entry(); print(after_main, gc.get_freeze_count())\n"
    )
    for torch, frozen in (("import torch\n", True), ("", False)):
        out = subprocess.run(
            [sys.executable, "-c", code.format(torch=torch)],
            capture_output=True, text=True, cwd=ROOT, timeout=120, check=True,
        ).stdout.splitlines()[-1].split()  # fmt: skip
        assert out[0] == "0" and (int(out[1]) > 0) == frozen, (torch, out)


# ---------------------------------------------------------------- bad input, refused
def _refused(got: subprocess.CompletedProcess, *said: str) -> None:
    """Exit 2, each of `said` in stderr, no traceback."""
    assert got.returncode == 2, (got.returncode, got.stderr[-2000:])
    assert "Traceback" not in got.stderr, got.stderr[-2000:]
    for text in said:
        assert text in got.stderr, (text, got.stderr[-2000:])


def test_a_config_that_does_not_read_and_flag_values_that_are_not_yaml_are_refused(tmp_path):
    """A config file of bytes that are not UTF-8, a folder given as the config, and a
    flag value that is not YAML (`{bad`, `[1`) ended in tracebacks (exit 1)."""
    from tests.harness import macb

    bad = tmp_path / "bad.yaml"
    bad.write_bytes(b"task: \xff\xfe\n")
    ok = tmp_path / "ok.yaml"
    ok.write_text("task: simple\nalgo: ddpg\nepisodes: 2\n")
    out = str(tmp_path / "out")
    for argv in (["train", "--config", str(bad)], ["run", str(bad), "--local"]):
        _refused(macb(*argv, "--out", out), f"{bad}: not UTF-8 text")
    _refused(macb("train", "--config", str(tmp_path), "--out", out), "a folder, not a config")
    _refused(macb("train", "--config", str(ok), "--task-kwargs", "{bad", "--out", out),
             "--task-kwargs '{bad': not a value")  # fmt: skip
    _refused(macb("run", str(ok), "--local", "--grid", "beta=[1", "--out", out),
             "--grid beta=[1: not a value")  # fmt: skip
    assert not Path(out).exists(), "nothing written"


def test_an_output_folder_that_cannot_be_written_is_refused_before_anything_runs(tmp_path):
    """`--out` naming a file or a folder that cannot be made, `--tensorboard` too, and a
    negative seed failed midway (a traceback, a half-made folder) or after training."""
    from tests.harness import macb

    ok = tmp_path / "ok.yaml"
    ok.write_text("task: simple\nalgo: ddpg\nepisodes: 2\n")
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    train = ("train", "--config", str(ok))
    _refused(macb(*train, "--out", str(a_file)), f"--out {a_file}: cannot write there")
    _refused(macb(*train, "--out", "/proc/macb-x"), "--out /proc/macb-x: cannot write there")
    (tmp_path / "link").symlink_to(tmp_path / "gone")
    _refused(macb(*train, "--out", str(tmp_path / "link")), "(a symbolic link to nothing)")
    out = tmp_path / "out"
    _refused(macb(*train, "--out", str(out), "--tensorboard", str(a_file)),
             f"--tensorboard {a_file}: cannot write there (a file, not a folder)")  # fmt: skip
    assert not out.exists(), "the run's folder is not made for a refused command"
    _refused(macb(*train, "--seeds", "-1", "--out", str(out)), "--seeds -1: seed")
    _refused(macb("run", str(ok), "--local", "--out", str(a_file)),
             f"{a_file}: cannot write there (a file, not a folder): nothing was run")  # fmt: skip
    assert not out.exists() and a_file.read_text() == ""


def test_macb_train_refuses_before_it_imports_torch(tmp_path):
    """A refusal of `macb train` answers at once: torch (seconds to import) is imported
    only once the config, the flags and the folder are found good."""
    ok = tmp_path / "ok.yaml"
    ok.write_text("task: simple\nalgo: ddpg\nepisodes: 2\n")
    code = (
        "import sys; from cli.main import main; rc = main(sys.argv[1:]); "
        "print('torch' in sys.modules, rc)"
    )
    for argv in (
        ["train", "--config", str(tmp_path / "none.yaml")],
        ["train", "--config", str(ok), "--episodes", "-3"],
        ["train", "--config", str(ok), "--out", "/proc/macb-x"],
        ["train", "--config", str(ok), "--seeds", "-1"],
        ["train", "--resume", str(tmp_path / "no-run")],
    ):
        got = subprocess.run(
            [sys.executable, "-c", code, *argv], cwd=ROOT, capture_output=True, text=True
        )
        assert got.stdout.split()[-2:] == ["False", "2"], (argv, got.stdout, got.stderr[-800:])
    # and one that trains does import it (the check above can fail)
    got = subprocess.run(
        [sys.executable, "-c", code, "train", "--config", str(ok), "--quiet",
         "--out", str(tmp_path / "run")],
        cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    assert got.stdout.split()[-2:] == ["True", "0"], (got.stdout, got.stderr[-800:])


def test_a_bus_endpoint_of_no_form_and_a_port_that_cannot_be_had_are_refused(tmp_path):
    """`--connect nonsense` ended in zenoh's ZError traceback; `macb view --port 70000`
    in an OverflowError, a port in use in uvicorn's exit 3."""
    import socket

    from tests.harness import macb

    _refused(macb("ps", "--connect", "nonsense"), "bus endpoints nonsense: Endpoints must be")
    run = tmp_path / "runs" / "r"
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps(make_config({}).model_dump(mode="json")))
    (run / "metrics.jsonl").write_text('{"episode": 4, "success_rate": 0.5}\n')
    _refused(macb("view", str(tmp_path), "--port", "70000"), "--port 70000: a port is from 0")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = str(taken.getsockname()[1])
        _refused(macb("view", str(tmp_path), "--port", port), f"cannot listen on 127.0.0.1:{port}")


def test_plot_db_only_reads_its_store_and_outputs_that_cannot_be_written_are_refused(tmp_path):
    """`macb plot --db` opened the file as the API's store: an empty file became a
    store and an older store was migrated in place (its API could no longer read it).
    It reads a copy now, as `macb export --db` does."""
    import hashlib
    import shutil

    from tests.harness import macb

    def digest(path: Path) -> str:
        return hashlib.sha256(path.read_bytes()).hexdigest()

    empty = tmp_path / "empty.db"
    empty.write_bytes(b"")
    _refused(macb("plot", "x", "-o", str(tmp_path / "p.png"), "--db", str(empty)),
             "not a macb API store")  # fmt: skip
    assert empty.read_bytes() == b"" and not (tmp_path / "p.png").exists()
    old = tmp_path / "old.db"
    shutil.copy(ROOT / "tests" / "data" / "api-store-schema1.sqlite3", old)
    before = digest(old)
    got = macb("plot", "xgrid", "-o", str(tmp_path / "p.png"), "--db", str(old))
    assert got.returncode == 0 and (tmp_path / "p.png").stat().st_size > 0, got.stderr
    assert digest(old) == before, "the store file is as it was"
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    _refused(macb("plot", "xgrid", "-o", str(a_file / "p.png"), "--db", str(old)),
             f"-o {a_file / 'p.png'}: cannot write there (a file, not a folder)")  # fmt: skip
    _refused(macb("export", "xgrid", "--db", str(old), "--csv", str(a_file)),
             f"--csv {a_file}: cannot write there (a file, not a folder)")  # fmt: skip
    for command in (["plot", "xgrid", "-o", str(tmp_path / "f.png")],
                    ["export", "xgrid", "--csv", str(tmp_path / "f")]):  # fmt: skip
        got = macb(*command, "--db", str(tmp_path))  # a folder: said so, no traceback
        _refused(got, f"{tmp_path}: a folder, not a store file")
        assert "Traceback" not in got.stderr
    # A command refused for its source (a run the store lacks, no store) leaves no folder
    # behind where it would have written.
    for argv in (["plot", "nosuch", "-o", str(tmp_path / "new" / "p.png"), "--db", str(old)],
                 ["export", "nosuch", "--csv", str(tmp_path / "new" / "csv"), "--tensorboard",
                  str(tmp_path / "new" / "tb"), "--db", str(old)],
                 ["export", "xgrid", "--csv", str(tmp_path / "new"), "--db",
                  str(tmp_path / "no.db")]):  # fmt: skip
        got = macb(*argv)
        assert got.returncode in (1, 2) and not (tmp_path / "new").exists(), got.stderr
    # A metric no row holds drew an empty figure and said "wrote" (exit 0).
    _refused(macb("plot", "xgrid", "-o", str(tmp_path / "q.png"), "--db", str(old),
                  "--metric", "nosuch"), "invalid choice: 'nosuch'")  # fmt: skip
    assert not (tmp_path / "q.png").exists()
    got = macb("run", "configs/fig8/sparse.yaml", "--local", "--seeds", "1", "1", "--out",
               str(tmp_path / "o"))  # fmt: skip
    _refused(got, "macb run: invalid config: seeds: a seed is repeated")
    assert got.stderr.count("config:") == 1, "named by the field, once"
    assert "pydantic" not in got.stderr, "the field and the reason, not pydantic's dump"


def test_a_files_seeds_note_is_said_only_when_one_run_is_what_runs(capsys):
    """`macb train --config sparse.yaml --seeds 5 6` said "this runs one run, seed 0"
    while it trained seeds 5 and 6."""
    from cli.config_flags import flag_dest, resolve_config

    args = argparse.Namespace(config=str(ROOT / "configs/fig8/sparse.yaml"), seeds=None)
    for name in TrainConfig.model_fields:
        setattr(args, flag_dest(name), None)
    resolve_config(args)
    assert "this runs one run, seed 0" in capsys.readouterr().err
    args.seeds = [5, 6]
    resolve_config(args)
    assert "this runs one run" not in capsys.readouterr().err


def test_counts_below_one_and_values_a_model_refuses_are_said_by_field(tmp_path):
    """`certs --actors -1` wrote a user set with no actor (exit 0); `start --actors 0`
    went on to the bus; reproduce/view `--seeds -1` and `serve api` with port 70000
    printed pydantic's dump (the latter with a traceback, exit 1)."""
    from tests.harness import macb

    _refused(macb("certs", str(tmp_path / "c"), "--actors", "-1"), "--actors: -1: at least 1")
    assert not (tmp_path / "c").exists()
    _refused(macb("start", "--actors", "0"), "--actors: 0: at least 1")
    for argv, said in (
        (["reproduce", "fig3", "--local", "--seeds", "-1", "--out", str(tmp_path / "o")],
         "macb reproduce: seeds.0: Input should be greater than or equal to 0"),
        (["serve", "api", "--listen-http", "127.0.0.1:70000"],
         "macb serve: port: Input should be less than or equal to 65535"),
        (["serve", "api", "--listen-http", "nonsense"],  # (said on stdout, before)
         "macb serve api: --listen-http wants HOST:PORT, not nonsense"),
    ):  # fmt: skip
        got = macb(*argv)
        _refused(got, said)
        assert "errors.pydantic.dev" not in got.stderr


@pytest.mark.parametrize("command", ["up", "start", "ls", "certs"])
def test_every_commands_help_says_its_defaults(command):
    """`up`, `start`, `ls`, `certs` (and plot, ps) were built without the formatter the
    others use, so their --help left the defaults out."""
    from tests.harness import macb

    got = macb(command, "--help")
    assert got.returncode == 0 and "(default: " in got.stdout, got.stdout


def test_lifetimes_limits_and_intervals_out_of_range_and_an_api_url_of_no_form(tmp_path):
    """`certs --days 99999999` left a key without its certificate (openssl's dump);
    `--days 0`, `ls --limit -3`, `train --cut-every -5` were taken; `ls --api notaurl`
    said httpx's words without naming the flag, and an unreachable API no URL."""
    from tests.harness import macb

    _refused(macb("certs", str(tmp_path / "c"), "--days", "99999999"), "--days 99999999: at most")
    _refused(macb("certs", str(tmp_path / "c"), "--days", "0"), "--days: 0: at least 1")
    assert not (tmp_path / "c").exists()
    (tmp_path / "f").write_text("x")  # a file where the folder should be: named, no errno
    _refused(macb("certs", str(tmp_path / "f")), f"{tmp_path / 'f'}: a file, not a folder")
    _refused(macb("ls", "--limit", "-3"), "--limit: -3: at least 1")
    _refused(macb("train", "--task", "simple", "--algo", "ddpg", "--cut-every", "-5",
                  "--out", str(tmp_path / "o")), "--cut-every -5: 0 or more")  # fmt: skip
    _refused(macb("ls", "--api", "notaurl"), "--api (or MACB_API_URL): not an http(s) URL")
    got = macb("ls", "--api", "http://127.0.0.1:1")
    assert got.returncode == 1 and "cannot reach the API at http://127.0.0.1:1" in got.stderr
    # An unreachable API: the runs are checked here, and an invalid one said first, exit 2.
    for text, why in (
        ("betaa: 0.3", "betaa: unknown key (misspelt?)"),
        ("arms: [{name: a, k: -1}]", "arms.0.k: Input should be greater than"),
    ):
        (tmp_path / "bad.yaml").write_text(text + "\n")
        got = macb("run", str(tmp_path / "bad.yaml"), "--api", "http://127.0.0.1:1")
        _refused(got, f"macb run: invalid config: {why}")
        assert "cannot reach" not in got.stderr


def test_flags_the_chosen_way_of_running_would_ignore_are_refused(tmp_path):
    """`run --local` took --detach, --api and --actors and ignored them, `run` without
    --local --group-size and --jobs, `train --resume` --seeds and --out, `view` without
    --figure the figure's flags; `view FILE` said "no such folder"."""
    from tests.harness import macb

    ok = tmp_path / "ok.yaml"
    ok.write_text("task: simple\nalgo: ddpg\nepisodes: 2\n")
    out = str(tmp_path / "o")
    _refused(macb("run", str(ok), "--local", "--detach", "--out", out),
             "--detach: not with --local")  # fmt: skip
    _refused(macb("run", str(ok), "--local", "--actors", "2", "--api", "http://x", "--out", out),
             "--api, --actors: not with --local")  # fmt: skip
    _refused(macb("run", str(ok), "--group-size", "2", "--jobs", "1"),
             "--group-size, --jobs: only with --local")  # fmt: skip
    assert not Path(out).exists()
    _refused(macb("train", "--resume", out, "--seeds", "1", "--out", "x"),
             "--resume takes the config from", "drop --seeds, --out")  # fmt: skip
    _refused(macb("view", str(tmp_path), "--seeds", "1"), "--seeds: only with --figure")
    _refused(macb("view", str(ok)), f"{ok}: a file, not a folder")
    # `up` without --run served until stopped and ignored the run's flags.
    _refused(macb("up", "--seeds", "1", "--out", out, "--beta", "0.5"),
             "--seeds, --out, --beta: with --run CONFIG")  # fmt: skip
    _refused(macb("up", "--launcher", "slurm", "--seeds", "1"),
             "--seeds: not with --launcher slurm")  # fmt: skip
    assert not Path(out).exists()
