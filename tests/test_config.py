"""Invalid configs are refused with the field and the reason, before anything runs."""

import json
import subprocess
import sys

import pytest

from shared.config import ConfigError, TrainConfig, load_config, make_config


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
    assert c.precision == "fp32"  # bf16 is opt-in until learning parity is shown


@pytest.mark.parametrize(
    "data, field, reason",
    [
        ({"task": "pong"}, "task", "Input should be"),
        ({"beta": -0.1}, "beta", "greater than or equal to 0"),
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


def test_cli_refuses_a_bad_config_before_running(tmp_path):
    out = tmp_path / "run"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "cli",
            "train",
            "--task",
            "simple",
            "--algo",
            "cen-maddpg",
            "--beta",
            "-1",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2
    assert "beta: Input should be greater than or equal to 0" in r.stderr
    assert not out.exists(), "nothing may run or be written"


def test_shipped_configs_are_valid():
    from pathlib import Path

    files = sorted(Path(__file__).parent.parent.glob("configs/**/*.yaml"))
    assert len(files) >= 30
    for f in files:
        cfg = load_config(f)
        json.dumps(cfg.model_dump(mode="json"))
