"""Invalid configs are refused with the field and the reason, before anything runs."""

import json
import re

import pytest

from shared.config import ConfigError, TrainConfig, load_config, make_config
from tests.harness import macb

CUSTOM = {"task": "mpe2.simple_speaker_listener_v4:parallel_env", "algo": "cen-maddpg"}


def test_defaults_are_the_thesis_settings():
    c = TrainConfig()
    assert (c.batch_size, c.buffer_size, c.learning_starts, c.episode_len) == (100, 10**6, 100, 20)
    assert (c.gamma, c.tau, c.lr_actor, c.lr_critic, c.hidden) == (
        0.99,
        0.005,
        1e-3,
        1e-3,
        (400, 300),
    )
    assert c.eval_every == 1 and c.eval_episodes == 10 and not c.time_limit_terminal
    assert c.precision == "fp32"  # the code's; bf16 is opt-in (docs/performance.md: parity)


@pytest.mark.parametrize(
    "data, field, reason",
    [
        ({"task": "pong"}, "task", "unknown task 'pong'"),
        ({"beta": -0.1}, "beta", "greater than or equal to 0"),
        # (nan and inf were said to be "less than or equal to 100")
        ({"beta": float("nan")}, "beta", "Input should be a finite number"),
        ({"tau": float("inf")}, "tau", "Input should be a finite number"),
        ({"k": 0}, "k", "greater than or equal to 1"),
        ({"task": "simple", "algo": "cen-maddpg"}, "config", "task simple has one"),
        ({"task": "spread", "algo": "ddpg"}, "config", "trains one agent"),
        ({"betta": 0.2}, "betta", "unknown key"),
        ({"episodes": "many"}, "episodes", "valid integer"),
        ({"explore": "maybe"}, "explore", "Input should be"),
        ({"precision": "fp16"}, "precision", "Input should be"),
        (
            {"precision": "bf16", "learner_impl": "reference"},
            "config",
            "precision bf16 needs learner_impl batched",
        ),
        # sizes past any run, which would fail only when the start is encoded (msgpack's
        # 64 bits) or the buffer allocated: refused here, naming the field
        ({"episodes": 2**64}, "episodes", "less than or equal to 100000000"),
        ({"eval_every": 10**30}, "eval_every", "less than or equal to 100000000"),
        ({"buffer_size": 10**12}, "buffer_size", "less than or equal to 1000000000"),
        ({"hidden": [64, 10**9]}, "config", "hidden sizes must be from 1 to 65536"),
        (
            {"beta_schedule": {"kind": "linear", "end": 0, "horizon": 10**30}},
            "beta_schedule.horizon",
            "less than or equal to",
        ),
        # a custom task's kwargs: plain data only (the store's JSON, HTTP's UTF-8, msgpack)
        (
            {**CUSTOM, "task_kwargs": {"render_mode": "\ud800"}},
            "task_kwargs",
            "task_kwargs.render_mode: a string that is not valid UTF-8",
        ),
        ({**CUSTOM, "task_kwargs": {"x": [1, float("nan")]}}, "task_kwargs", "x[1]: nan is not"),
        ({**CUSTOM, "task_kwargs": {"n": 2**70}}, "task_kwargs", "does not fit in 64 bits"),
        ({**CUSTOM, "task_kwargs": {"when": {1, 2}}}, "task_kwargs", "a set is not plain data"),
    ],
)
def test_invalid_configs_name_field_and_reason(data, field, reason):
    with pytest.raises(ConfigError) as err:
        make_config(data)
    msg = str(err.value)
    assert msg.startswith(f"{field}:") or f"; {field}:" in msg, msg
    assert reason in msg


def test_config_file_and_overrides(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("task: spread\nagents: 3\nalgo: dis-maddpg\nexplore: dis-macb\nk: 64\n")
    c = load_config(p, {"beta": 0.7})
    assert (c.task, c.agents, c.n_agents, c.k, c.beta) == ("spread", 3, 3, 64, 0.7)
    p.write_text("- not\n- a mapping\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(p)
    for empty in ("", "# only a comment\n", "{}\n"):  # not "every default": another file was meant
        p.write_text(empty)
        with pytest.raises(ConfigError, match="c.yaml: empty: a config file holds at least"):
            load_config(p)


def test_cli_refuses_a_bad_config_before_running(tmp_path):
    out = tmp_path / "run"
    r = macb("train", "--task", "simple", "--algo", "cen-maddpg", "--beta", "-1", "--out", str(out))
    assert r.returncode == 2
    assert "beta: Input should be greater than or equal to 0" in r.stderr
    assert not out.exists(), "nothing may run or be written"


def test_shipped_configs_are_valid():
    from pathlib import Path

    from cli.config_flags import one_run_config
    from cli.local import expand_body
    from shared.config import read_config_file

    files = sorted(Path(__file__).parent.parent.glob("configs/**/*.yaml"))
    assert len(files) >= 30
    for f in files:
        if "arms" in read_config_file(f):  # an experiment of several runs: each is valid
            _, _, runs = expand_body(read_config_file(f))
            assert len({r.arm for r in runs}) == len(read_config_file(f)["arms"]) > 1, f
            for run in runs:
                json.dumps(run.config.model_dump(mode="json"))
            continue
        cfg, _ = one_run_config(str(f), {})  # an experiment file, as one run takes it
        json.dumps(cfg.model_dump(mode="json"))
        if f.parent.name != "configs":  # the thesis's experiments run 3 seeds, as it did
            assert read_config_file(f)["seeds"] == [0, 1, 2], f


def test_profile_thesis_sets_the_task_and_collection_options_a_config_does_not_give():
    """The task-level options of docs/fidelity.md (T3, T4, T7, T8, T12, T13, T16, L1):
    mpe2's behaviour by default, the thesis code's under profile thesis, a given value
    kept either way."""
    names = ("success_terminal", "cover", "landmark_size", "pad_obs", "comm_obs")
    names += ("integrator", "warmup", "time_limit_terminal")

    def options(**kw):
        c = make_config(kw)
        return tuple(getattr(c, n) for n in names)

    mpe2 = (False, "sum", None, False, True, "position-first", "policy", False)
    thesis = (True, "landmark", 0.075, True, False, "velocity-first", "random", True)
    assert options() == options(profile="mpe2") == mpe2
    assert options(profile="thesis") == thesis  # speaker_listener by default
    spread = options(profile="thesis", task="spread", algo="cen-maddpg")
    assert spread == thesis[:2] + (None,) + thesis[3:]  # navigation keeps 0.125
    assert options(profile="thesis", pad_obs=False, warmup="policy", landmark_size=0.04) == (
        True,
        "landmark",
        0.04,
        False,
        False,
        "velocity-first",
        "policy",
        True,
    )
    assert options(success_terminal=True, integrator="velocity-first")[:6] == (
        True,
        "sum",
        None,
        False,
        True,
        "velocity-first",
    )


@pytest.mark.parametrize(
    ("data", "says"),
    [
        ({"threads": True}, "threads: a number, not true"),
        ({"episodes": False}, "episodes: a number, not false"),
        ({"beta": True}, "beta: a number, not true"),
        ({"hidden": [True, 64]}, "hidden.0: a number, not true"),
        ({"early_stop": {"rule": "no_improvement", "patience": True}}, "early_stop.patience"),
    ],
)
def test_a_boolean_is_no_number(data, says):
    """Lax pydantic read true and false as 1 and 0 (`threads: yes` in YAML ran one
    thread; the API's fuzzing found `"threads": true` accepted): refused, named."""
    with pytest.raises(ConfigError, match=re.escape(says)):
        make_config({"task": "simple", "algo": "ddpg", **data})
