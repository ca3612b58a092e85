"""The counter service's parts in process, no bus: a burst's plan by the exactly-once
rule, buffered and committed; a run's snapshot plus its log giving back the same counts;
bonus queries answered and the service thread stepping aside for them; runs' folders
resumed, archived and restored; the stats and the snapshot schedule."""

from __future__ import annotations

import json
import logging
import threading
import time

import numpy as np
import pytest

from services.counter import bonus, burst, snapshot
from services.counter.runs import Runs
from services.counter.state import RunState
from services.counter.stats import run_stats, update_rate
from shared.config import make_config
from shared.envs.tasks import task_spec_for
from shared.net.messages import Assignment, BonusQuery, BonusReply
from shared.net.protocol import ReceiveCursor
from shared.net.wire import WireError, decode
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


def test_a_snapshot_npz_from_before_still_loads_and_a_corrupt_one_is_refused_by_name(tmp_path):
    """Format 1 (snapshot.npz: keys, counts and a JSON meta) is read; the next snapshot
    replaces it with snapshot.pt. A snapshot that does not read names its file."""
    st = new_run(tmp_path / "r")
    o, a = rows(12, 3, st.obs_dim, st.act_dim)
    count(st, "a0", 0, o, a)
    arrays = {}
    for t, table in enumerate(st.explorer.tables):
        arrays[f"keys{t}"], arrays[f"counts{t}"] = table.to_arrays()
    meta = {"format": 1, "run": "r", "expected": {"a0": 12},
            "totals": [t.total for t in st.explorer.tables],
            "stats": {"counted": 12, "duplicates": 0, "gaps": 0, "snapshots": 1}}  # fmt: skip
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez(tmp_path / "r" / "snapshot.npz", **arrays)
    st.wal.close()

    again = new_run(tmp_path / "r")
    assert snapshot.exists(tmp_path / "r")
    snapshot.load(again)
    assert again.counted == 12 and again.cursor.positions() == {"a0": 12}
    for mine, theirs in zip(again.explorer.counts(o, a), st.explorer.counts(o, a)):
        assert np.array_equal(mine, theirs)
    snapshot.write("r", again)
    assert sorted(p.name for p in (tmp_path / "r").glob("snapshot*")) == ["snapshot.pt"]
    # a version of before ran on the folder since: its newer snapshot.npz is the one read
    arrays["meta"] = np.frombuffer(
        json.dumps({**meta, "time": time.time() + 60, "expected": {"a0": 7}}).encode(), np.uint8
    )
    np.savez(tmp_path / "r" / "snapshot.npz", **arrays)
    newer = new_run(tmp_path / "r")
    snapshot.load(newer)
    assert newer.cursor.positions() == {"a0": 7}
    (tmp_path / "r" / "snapshot.npz").unlink()

    (tmp_path / "r" / "snapshot.pt").write_bytes(b"not a snapshot")
    with pytest.raises(ValueError, match="snapshot.pt: unreadable"):
        snapshot.load(new_run(tmp_path / "r"))


# ------------------------------------------------------------ a burst: buffered, committed
def test_a_pending_burst_fills_ages_and_is_taken_by_run_in_arrival_order(tmp_path):
    st1, st2 = new_run(tmp_path / "r1"), new_run(tmp_path / "r2")
    o, a = rows(4, 1, st1.obs_dim, st1.act_dim)
    pending = burst.Pending(max_rows=10, max_wait_s=0.5)
    assert not pending.due(100.0)  # nothing buffered: never due
    assert not pending.add("r2", st2, ("a0", 0, o, a), now=100.0)
    assert not pending.add("r1", st1, ("a0", 0, o, a), now=100.3)
    assert not pending.due(100.4) and pending.due(100.5)  # the oldest's age counts
    assert pending.add("r2", st2, ("a1", 0, o, a), now=100.6)  # 12 rows >= 10: full
    taken = pending.take()
    assert list(taken) == ["r2", "r1"]
    assert taken["r2"][0] is st2 and [b[0] for b in taken["r2"][1]] == ["a0", "a1"]
    assert pending.rows == 0 and not pending.runs and not pending.due(200.0)


def test_a_commit_logs_counts_and_moves_the_cursor_once_and_gives_queries_their_turns(tmp_path):
    st = new_run(tmp_path / "r")
    o, a = rows(8, 2, st.obs_dim, st.act_dim)
    plan = burst.plan(st.cursor, [("a0", 0, o[:5], a[:5]), ("a1", 0, o[5:], a[5:])])
    turns = []
    burst.commit(st, plan, threading.RLock(), lambda: turns.append(1))
    assert len(turns) == 3  # before hashing, logging and counting
    assert st.counted == 8 and st.dirty and st.cursor.positions() == {"a0": 5, "a1": 3}
    assert st.wal.records == 2  # a record per actor of the burst (in one write)
    want = build_exploration(st.config, task_spec_for(st.config))
    want.observe(o, a)
    for mine, theirs in zip(st.explorer.counts(o, a), want.counts(o, a)):
        assert np.array_equal(mine, theirs)

    again = burst.plan(st.cursor, [("a0", 0, o[:5], a[:5])])  # a resend: nothing new
    burst.commit(st, again, threading.RLock(), lambda: turns.append(1))
    assert len(turns) == 3 and st.counted == 8 and st.wal.records == 2
    assert st.cursor.duplicate_rows == 5  # only the tally changed


# ------------------------------------------------------------ bonus queries
def query(st: RunState, obs, act) -> BonusQuery:
    return BonusQuery("r", obs=obs, act=act)


def test_a_bonus_query_is_answered_from_the_counts_and_tallies_rows_never_counted(tmp_path):
    st = new_run(tmp_path / "r")
    o, a = rows(6, 3, st.obs_dim, st.act_dim)
    count(st, "a0", 0, o[:4], a[:4])
    count(st, "a0", 4, o[:2], a[:2])  # rows 0-1 twice
    msg = query(st, o, a)
    bonus.check(st, msg)
    reply = decode(bonus.answer(st, msg, threading.RLock(), time.perf_counter(), "c0"), BonusReply)
    assert reply.service == "c0"  # (the learner takes only its run's counter's reply)
    assert reply.counts.shape == (len(st.explorer.tables), 6)
    for table_counts, want in zip(reply.counts, st.explorer.counts(o, a)):
        assert np.array_equal(table_counts, want)
    assert reply.bonus.shape[0] == 6 and np.all(np.isfinite(reply.bonus))
    assert reply.tables["table_size"] > 0
    assert st.queries == 1 and len(st.latencies) == 1
    assert st.uncounted_rows_queried == 2  # rows 4 and 5 were never counted

    st.closed = True  # stopped while the query was on its way: no reply
    assert bonus.answer(st, msg, threading.RLock(), time.perf_counter(), "c0") is None


def test_a_bonus_query_of_another_shape_is_refused(tmp_path):
    st = new_run(tmp_path / "r")
    o, a = rows(6, 3, st.obs_dim, st.act_dim)
    with pytest.raises(WireError, match="same B"):
        bonus.check(st, query(st, o, a[:5]))
    with pytest.raises(WireError, match="bonus_query"):
        bonus.check(st, query(st, o[0], a[0]))
    with pytest.raises(WireError):
        bonus.check(st, query(st, o[:, :3], a))


def test_the_service_thread_steps_aside_only_while_a_query_is_answered():
    # A bound far above any stall of a loaded machine, so that a wait to the bound cannot
    # pass for no wait, nor a thread let go at its bound for one let go by the answer.
    gate = bonus.QueryGate(max_wait_s=60)
    t0 = time.monotonic()
    gate.step_aside()
    assert time.monotonic() - t0 < 30  # no query: no wait
    bounded = bonus.QueryGate(max_wait_s=0.2)
    with bounded.answering():
        t0 = time.monotonic()
        bounded.step_aside()
        assert time.monotonic() - t0 >= 0.19  # waits, but no longer than its bound
    done = threading.Event()
    with gate.answering():

        def service_thread() -> None:
            gate.step_aside()
            done.set()

        threading.Thread(target=service_thread, daemon=True).start()
        assert not done.wait(0.05)  # held while the query is answered ...
    assert done.wait(30)  # ... and let go when it is (long before its bound)


# ------------------------------------------------------------ runs on disk
CONFIG = {"task": "speaker_listener", "explore": "dis-macb", "k": 32}
ASSIGN = Assignment.from_wire({"counter": "c0", "learner": "L", "actors": ["a0"]})


def test_a_runs_folder_is_resumed_for_the_same_config_and_archived_otherwise(tmp_path, caplog):
    runs = Runs(tmp_path, logging.getLogger("t"))
    cfg = make_config(CONFIG)
    with pytest.raises(ValueError, match="safe directory"):
        runs.prepare("../x", cfg, ASSIGN)
    path = runs.prepare("r", cfg, ASSIGN)
    st, replayed = runs.open("r", cfg, path)
    assert replayed == 0 and st.learner == "L" and runs.get("r") is st
    assert json.loads((path / "assign.json").read_text()) == ASSIGN.to_wire()  # the map
    o, a = rows(5, 4, st.obs_dim, st.act_dim)
    count(st, "a0", 0, o, a)
    runs.close("r")
    assert st.closed and runs.get("r") is None

    again, replayed = runs.open("r", cfg, runs.prepare("r", cfg, ASSIGN))
    assert replayed == 1 and again.counted == 5  # same config: resumed from its log
    assert (path / "snapshot.pt").exists()  # the log folded into a snapshot at once
    runs.close("r")

    (path / "assign.json").write_text('{"learner": "L"}')  # no actors: refused, not followed
    again, _ = runs.open("r", cfg, path)
    assert again.learner is None and again.counted == 5
    runs.close("r")

    # Written before a key existed (here: beta_schedule missing, its default): the same run.
    saved = json.loads((path / "config.json").read_text())
    assert saved.pop("beta_schedule") == cfg.model_dump(mode="json")["beta_schedule"]
    (path / "config.json").write_text(json.dumps(saved))
    again, replayed = runs.open("r", cfg, runs.prepare("r", cfg, ASSIGN))
    assert again.counted == 5 and not (tmp_path / ".archive").exists()
    runs.close("r")

    other = make_config({**CONFIG, "k": 16})
    with caplog.at_level(logging.WARNING):
        fresh, _ = runs.open("r", other, runs.prepare("r", other, ASSIGN))
    assert "had another config (k: " in caplog.text
    assert fresh.counted == 0 and len(list((tmp_path / ".archive").iterdir())) == 1
    runs.mark_stopped("r", fresh, "done")
    runs.close("r")
    st3, _ = runs.open("r", other, runs.prepare("r", other, ASSIGN))  # stopped: afresh
    assert st3.counted == 0 and len(list((tmp_path / ".archive").iterdir())) == 2
    runs.close("r")


def test_a_runs_folder_of_another_attempt_is_archived_not_resumed(tmp_path, caplog):
    """A start of attempt 2 finding attempt 1's unfinished folder (its stop never came,
    a restore that failed left it) starts afresh: attempt 1's tables and positions must
    not meet attempt 2's transitions, numbered from 0 again. A start or a folder that
    names no attempt (an older peer's) is taken as the same attempt."""
    runs = Runs(tmp_path, logging.getLogger("t"))
    cfg = make_config(CONFIG)
    st, _ = runs.open("r", cfg, runs.prepare("r", cfg, ASSIGN, 1))
    o, a = rows(5, 4, st.obs_dim, st.act_dim)
    count(st, "a0", 0, o, a)
    runs.close("r")
    for attempt, counted in ((1, 5), (2, 0), (2, 3), (None, 3)):
        st, _ = runs.open("r", cfg, runs.prepare("r", cfg, ASSIGN, attempt))
        assert st.counted == counted, attempt
        if st.counted == 0:
            count(st, "a0", 0, o[:3], a[:3])
        runs.close("r")
    assert len(list((tmp_path / ".archive").iterdir())) == 1
    assert "run r was attempt 1, not 2: old state moved to" in caplog.text
    assert runs.attempt("r") is None  # (as the last start named it)


def test_restore_opens_every_unfinished_run_and_skips_the_rest(tmp_path):
    runs = Runs(tmp_path, logging.getLogger("t"))
    cfg = make_config(CONFIG)
    for run in ("a", "b", "c"):
        st, _ = runs.open(run, cfg, runs.prepare(run, cfg, ASSIGN))
        o, a = rows(3, 5, st.obs_dim, st.act_dim)
        count(st, "a0", 0, o, a)
    runs.mark_stopped("b", runs.get("b"), "done")
    for run in ("a", "b", "c"):
        runs.close(run)
    (tmp_path / "c" / "config.json").write_text('{"task": "no-such-task"}')
    (tmp_path / "d").mkdir()  # no config: not a run

    again = Runs(tmp_path, logging.getLogger("t"))
    restored = again.restore_all()
    assert [(run, st.counted) for run, _, st in restored] == [("a", 3)]
    assert again.restored == {"a"} and again.get("c") is None
    again.close("a")
    assert again.restored == set()


def test_a_run_takes_batches_by_the_learners_rule_of_its_actors_alone(tmp_path, caplog):
    """The counter counts only what the learner can take: its actors' batches, whole
    (an overlap is refused, not taken for its tail), before and after a restore; a
    restored position of an actor the run no longer names is let go."""
    runs = Runs(tmp_path, logging.getLogger("t"))
    cfg = make_config(CONFIG)
    two = Assignment.from_wire({"counter": "c0", "learner": "L", "actors": ["a0", "a1"]})
    st, _ = runs.open("r", cfg, runs.prepare("r", cfg, two))
    assert st.actors == ("a0", "a1") and st.cursor.positions() == {"a0": 0, "a1": 0}
    assert not st.cursor.knows("a2")
    o, a = rows(10, 5, st.obs_dim, st.act_dim)
    count(st, "a0", 0, o[:5], a[:5])
    count(st, "a1", 0, o[:5], a[:5])
    assert not burst.plan(st.cursor, [("a0", 3, o, a)]).segments  # an overlap: refused whole
    runs.close("r")

    again, _ = runs.open("r", cfg, runs.prepare("r", cfg, ASSIGN))  # a0 alone now
    assert again.cursor.positions() == {"a0": 5} and again.counted == 10
    assert not again.cursor.knows("a1") and not again.cursor.partial
    assert "positions of ['a1'], not of its actors, let go" in caplog.text
    runs.close("r")


# ------------------------------------------------------------ stats, snapshot schedule
def test_stats_report_the_tables_the_tallies_and_the_query_latency(tmp_path):
    st = new_run(tmp_path / "r")
    o, a = rows(10, 6, st.obs_dim, st.act_dim)
    count(st, "a0", 0, o, a)
    st.latencies.extend([0.001, 0.002, 0.003])
    st.rate_t, st.rate_counted = 10.0, 0
    update_rate(st, 12.0)
    assert st.rate == 5.0 and st.rate_counted == 10 and st.rate_t == 12.0
    s = run_stats(st, rejects_total=7)
    assert s.counted_transitions == 10 and s.rejects_total == 7 and s.actors == 1
    assert s.transitions_per_sec == 5.0 and s.query_p50_ms == pytest.approx(2.0)
    assert s.table_size > 0 and s.memory_bytes > 0 and s.wal_records == 1


def test_a_timed_snapshot_waits_for_changes_and_a_big_enough_log(tmp_path):
    st = new_run(tmp_path / "r")
    assert not snapshot.due(st)  # nothing changed
    o, a = rows(50, 7, st.obs_dim, st.act_dim)
    count(st, "a0", 0, o, a)
    st.dirty = True
    assert snapshot.due(st)  # the log holds every key: as big as the snapshot
    snapshot.write("r", st)
    assert not snapshot.due(st)
    assert snapshot.next_check(100.0, 5.0, 0.01) == 105.0
    assert snapshot.next_check(100.0, 5.0, 1.0) == 100.0 + snapshot.SNAPSHOT_SPACING
