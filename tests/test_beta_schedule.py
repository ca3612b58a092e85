"""`beta_schedule` (beyond the thesis: its §7 suggests a decaying beta): the bonus scale
moves from `beta` to `end` over a horizon, every pricing site asks the config's
`beta_at`, the rows record the beta in force, and the default is today's run bit for
bit. The group and lockstep cluster cases are in test_group_trainer.py and
test_lockstep.py."""

from __future__ import annotations

import pytest

from cli.trainer import train
from shared.config import ConfigError, make_config

TIMING = ("steps_per_sec", "train_steps_per_sec", "wall_s")
BASE = {
    "task": "simple",
    "algo": "ddpg",
    "hidden": [16, 16],
    "episodes": 8,
    "episode_len": 10,
    "eval_every": 2,
    "eval_episodes": 2,
    "learning_starts": 20,
    "batch_size": 8,
    "learner_lanes": 1,
    "k": 8,
}


def strip(rows):
    return [{k: v for k, v in r.items() if k not in TIMING} for r in rows]


def test_the_schedule_moves_beta_from_beta_to_end_over_its_horizon():
    lin = make_config({**BASE, "beta_schedule": {"kind": "linear", "end": 0.0, "horizon": 4}})
    # transition s belongs to episode (s - 1) // 10 + 1; the episodes before it count
    assert [lin.beta_at(s) for s in (1, 10, 11, 20, 21, 40, 41, 400)] == pytest.approx(
        [0.8, 0.8, 0.6, 0.6, 0.4, 0.2, 0.0, 0.0]
    )
    exp = make_config(
        {
            **BASE,
            "beta_schedule": {"kind": "exponential", "end": 0.2, "horizon": 2, "unit": "steps"},
        }
    )
    assert [exp.beta_at(s) for s in (0, 1, 2, 3)] == pytest.approx([0.8, 0.4, 0.2, 0.2])
    assert make_config(BASE).beta_at(10**9) == 0.8


@pytest.mark.parametrize(
    ("schedule", "extra", "says"),
    [
        ({"kind": "linear", "end": 0.1}, {}, "beta_schedule.horizon: kind linear needs"),
        ({"kind": "linear", "end": 0.1, "horizon": 0}, {}, "beta_schedule.horizon: Input"),
        ({"kind": "linear", "end": -0.1, "horizon": 5}, {}, "beta_schedule.end: Input"),
        ({"kind": "constant", "end": 0.1}, {}, "beta_schedule.end: a constant schedule"),
        ({"kind": "exponential", "end": 0.0, "horizon": 5}, {}, "never reaches 0"),
        ({"kind": "exponential", "end": 0.1, "horizon": 5}, {"beta": 0.0}, "from beta 0"),
        ({"kind": "linear", "end": 0.1, "horizon": 5}, {"explore": "none"}, "no bonus"),
        ({"kind": "cosine"}, {}, "beta_schedule.kind: Input should be"),
        (
            {"kind": "linear", "end": 0.1, "horizon": 5, "every": 2},
            {},
            "beta_schedule.every: unknown key",
        ),
    ],
)
def test_invalid_schedules_are_refused_naming_the_field_and_the_reason(schedule, extra, says):
    with pytest.raises(ConfigError, match=says.replace(".", r"\.")):
        make_config({**BASE, **extra, "beta_schedule": schedule})


def test_the_default_and_a_constant_schedule_are_todays_run_bit_for_bit(tmp_path):
    plain = train(make_config(BASE), tmp_path / "a", progress=False)
    const = train(
        make_config({**BASE, "beta_schedule": {"kind": "constant"}}), tmp_path / "b", progress=False
    )
    assert "beta" not in plain[0]  # a run without the key writes the rows it always did
    assert all(r.pop("beta") == 0.8 for r in const)
    assert strip(plain) == strip(const)


def test_a_decaying_beta_prices_every_update_and_the_rows_record_it(tmp_path):
    """The constant control on a linear schedule: every sampled row's bonus is the beta of
    the update's transition, so a point's bonus mean lies between the betas of the
    episodes it trained in, and its rows' beta is the schedule's at the point."""
    schedule = {"kind": "linear", "end": 0.0, "horizon": 4}
    cfg = make_config({**BASE, "explore": "constant", "beta_schedule": schedule})
    rows = train(cfg, tmp_path / "c", progress=False)
    assert [r["beta"] for r in rows] == pytest.approx([0.6, 0.2, 0.0, 0.0])
    means = [r["bonus_mean"] for r in rows]
    assert means[0] == 0.0  # no update before transition 21
    # transitions 21..40: episodes 3 and 4, after 2 and 3 episodes: 0.4 and 0.2
    assert means[1] == pytest.approx(0.3) and means[2] == pytest.approx(0.0, abs=1e-7)
    assert rows[1]["bonus_std"] == pytest.approx(0.1)  # two betas in one point's updates
    counting = make_config({**BASE, "explore": "dis-macb", "beta_schedule": schedule})
    fixed = train(make_config({**BASE, "explore": "dis-macb"}), tmp_path / "f", progress=False)
    moved = train(counting, tmp_path / "m", progress=False)
    assert 0 < moved[1]["bonus_mean"] < fixed[1]["bonus_mean"]
    assert strip(moved) != strip(fixed)
