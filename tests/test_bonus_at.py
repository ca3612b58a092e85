"""`bonus_at: collection` and `hash: raw`: the thesis code's fig. 3 loop (SMADDPG at
commit 92fc6f5), beside the sample-time pricing of the thesis text.

At collection a transition is counted, then priced from its count (itself included),
and the bonus is stored with it: every later sample of it reads the same bonus. `raw`
keys are the counted vector's float32 bytes, so continuous observations make every key
new and the stored bonus is beta on every transition."""

from __future__ import annotations

import numpy as np
import pytest

from cli.trainer import GroupRun, train
from shared.config import ConfigError, make_config
from shared.core.counting import count_bonus
from shared.core.exploration import CountExploration, ExploreSpec
from shared.core.simhash import RawKey
from shared.envs.tasks import task_spec_for
from shared.run.factories import build_exploration

BASE = {"task": "simple", "algo": "ddpg", "hidden": [16, 16], "learning_starts": 30,
        "batch_size": 8, "learner_lanes": 1, "episodes": 4, "eval_every": 2}  # fmt: skip


def test_raw_keys_are_the_float32_bytes():
    keys = RawKey(2).keys(np.array([[0.5, -0.0], [0.5, 0.0], [0.5, 1e-7]], np.float32))
    assert bytes(keys[0]) == bytes(keys[1]) != bytes(keys[2])
    assert keys.shape == (3, 8)
    with pytest.raises(ValueError, match="expected"):
        RawKey(3).keys(np.zeros((2, 2)))
    ex = CountExploration(ExploreSpec(mode="dis-macb", hash="raw", key="state"), (4,), (2,))
    obs, act = np.ones((1, 4), np.float32), np.zeros((1, 2), np.float32)
    ex.observe(obs, act)
    ex.observe(obs, act + 1)  # the action is not in a state key
    assert ex.counts(obs, act)[0].tolist() == [2]


def test_bonus_stored_at_collection_is_priced_from_the_count_then():
    cfg = make_config({**BASE, "explore": "dis-macb", "k": 2, "beta": 0.8,
                       "bonus_at": "collection"})  # fmt: skip
    group = GroupRun([cfg], [None], 60.0)
    run = group.members[0]
    shadow = build_exploration(cfg, task_spec_for(cfg))  # the run's tables, counted anew
    expected = []
    group.episode()  # 20 steps: collection only (learning starts after 30)
    for i in range(20):
        o, a = run.buffer.obs[i : i + 1], run.buffer.act[i : i + 1]
        shadow.observe(o, a)
        expected.append(count_bonus(shadow.counts(o, a)[0], 0.8)[0])
    np.testing.assert_allclose(run.buffer.bonus[:20, 0], expected, rtol=0, atol=0)
    assert run.buffer.bonus[:20].min() < 0.8, "2-bit keys repeat: some counts above 1"
    b = run.buffer.sample(5, np.random.default_rng(0))
    np.testing.assert_array_equal(b.bonus, run.buffer.bonus[b.idx])


def test_raw_keys_at_collection_store_beta_on_every_transition(tmp_path):
    cfg = make_config({**BASE, "explore": "dis-macb", "hash": "raw", "key": "state",
                       "beta": 1.2, "bonus_at": "collection"})  # fmt: skip
    rows = train(cfg, tmp_path / "run", progress=False)
    for r in rows:
        assert r["bonus_mean"] == pytest.approx(1.2) and r["bonus_std"] == pytest.approx(0.0)
        assert r["sampled_count1_pct"] == 100.0


def test_sample_time_pricing_is_unchanged_by_default():
    cfg = make_config({**BASE, "explore": "dis-macb"})
    assert cfg.bonus_at == "sample"
    assert GroupRun([cfg], [None], 60.0).members[0].buffer.bonus is None


def test_bad_values_are_refused_naming_the_field():
    with pytest.raises(ConfigError, match="bonus_at"):
        make_config({**BASE, "bonus_at": "later"})
    with pytest.raises(ConfigError, match="hash"):
        make_config({**BASE, "hash": "md5"})
