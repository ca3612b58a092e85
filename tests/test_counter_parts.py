"""The counter service's pure parts in process, no bus: a burst's plan by the
exactly-once rule, and a run's snapshot plus its log giving back the same counts."""

from __future__ import annotations

import logging

import numpy as np

from services.counter import burst, snapshot
from services.counter.state import RunState
from shared.config import make_config
from shared.envs.tasks import task_spec_for
from shared.net.protocol import ReceiveCursor
from shared.persist.wal import WriteAheadLog
from shared.run.factories import build_exploration


def rows(n: int, seed: int, obs_dim: int = 4, act_dim: int = 2):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, obs_dim)).astype(np.float32), rng.uniform(size=(n, act_dim)).astype(
        np.float32
    )


def test_a_burst_takes_each_actors_new_rows_as_one_range_and_leaves_the_cursor_alone():
    cursor = ReceiveCursor({"a0": 0, "a1": 5})
    o1, a1 = rows(5, 1)
    o2, a2 = rows(5, 2)
    o3, a3 = rows(5, 3)
    plan = burst.plan(
        cursor,
        [
            ("a0", 0, o1, a1),  # new
            ("a0", 0, o1, a1),  # a resend: nothing new
            ("a0", 3, o2, a2),  # overlaps: rows 5..7 are new
            ("a1", 20, o3, a3),  # a gap: dropped
            ("a1", 5, o3, a3),  # new
        ],
    )
    assert plan.segments == [("a0", 0, 8), ("a1", 5, 5)] and plan.rows == 13
    assert np.array_equal(plan.obs, np.concatenate([o1, o2[2:], o3]))
    assert np.array_equal(plan.act, np.concatenate([a1, a2[2:], a3]))
    assert plan.staged.positions() == {"a0": 8, "a1": 10}
    assert cursor.positions() == {"a0": 0, "a1": 5}  # decided on a copy
    nothing = burst.plan(cursor, [("a0", 20, o1, a1)])
    assert nothing.obs is None and nothing.segments == [] and nothing.staged.gaps == 1


def new_run(path) -> RunState:
    cfg = make_config({"task": "speaker_listener", "explore": "dis-macb", "k": 32})
    spec = task_spec_for(cfg)
    path.mkdir(parents=True, exist_ok=True)
    wal, _ = WriteAheadLog.open(path / "log.wal")
    return RunState(cfg, build_exploration(cfg, spec), spec.joint_obs_dim, spec.joint_act_dim,
                    path, wal)  # fmt: skip


def count(st: RunState, actor: str, seq: int, obs, act) -> None:
    """What the service does with a taken batch: log, count, move the cursor."""
    keys = st.explorer.keys(obs, act)
    st.wal.append_many([(actor, seq, len(obs), keys)])
    for table, k in zip(st.explorer.tables, keys):
        table.increment(k)
    st.cursor.take(actor, seq, len(obs))
    st.counted += len(obs)


def test_a_snapshot_and_the_log_beyond_it_give_the_same_counts_back(tmp_path):
    st = new_run(tmp_path / "r")
    o, a = rows(30, 7, st.obs_dim, st.act_dim)
    count(st, "a0", 0, o[:20], a[:20])
    snapshot.write("r", st)  # the log is emptied
    count(st, "a0", 20, o[20:], a[20:])
    st.wal.close()

    again = new_run(tmp_path / "r")
    _, records = WriteAheadLog.open(tmp_path / "r" / "log.wal")
    snapshot.load(again)
    assert again.counted == 20 and again.cursor.positions() == {"a0": 20}
    assert snapshot.replay("r", again, records + records, logging.getLogger("t")) == 1
    assert again.counted == 30 and again.cursor.positions() == {"a0": 30}
    for mine, theirs in zip(again.explorer.counts(o, a), st.explorer.counts(o, a)):
        assert np.array_equal(mine, theirs)
    assert snapshot.size(again) > 0
