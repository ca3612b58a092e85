"""The counter service against a real router and a real `macb serve counter` process.

The test plays the actors and the learner: it publishes numbered transition batches
(one episode each, `episode_len` rows, as actors do: the counter takes no other, as the
learner takes no other), watches the counter's acks and asks it for bonuses. Expected
counts come from a CountExploration built in the test with the run's config (same
SimHash seed), fed the unique transitions, so every reply is checked exactly, not just
its shape.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict

import msgpack
import numpy as np
import pytest
import torch

from shared.config import make_config
from shared.envs.tasks import task_spec_for
from shared.net.bus import Replies, k_ack, k_bonus, k_control, k_info, k_status, k_transitions
from shared.net.messages import (
    Ack,
    Assignment,
    BonusQuery,
    BonusReply,
    Start,
    Status,
    Stop,
    Transitions,
)
from shared.net.wire import SCHEMA_VERSION, decode, encode
from shared.persist.wal import WriteAheadLog, read_wal
from shared.run.factories import build_exploration
from tests.conftest import wait_for
from tests.harness import ROOT

OBS, ACT = 14, 5  # speaker_listener: joint obs 3 + 11, joint act 3 + 2
ASSIGN = Assignment.from_wire(
    {"counter": "c0", "learner": "L", "actors": ["a0", "a1"], "evaluator": "e"}
)
BASE = {
    "task": "speaker_listener",
    "algo": "cen-maddpg",
    "explore": "cen-macb",
    "k": 64,
    "episode_len": 5,
}


class Stream:
    """One actor's transitions, numbered from 0; batches are slices of it."""

    def __init__(self, seed: int, n: int) -> None:
        rng = np.random.default_rng(seed)
        self.obs = rng.uniform(-1, 1, (n, OBS)).astype(np.float32)
        self.act = rng.uniform(-1, 1, (n, ACT)).astype(np.float32)

    def __len__(self) -> int:
        return len(self.obs)


def transitions(run: str, actor: str, seq: int, obs: np.ndarray, act: np.ndarray) -> bytes:
    n = len(obs)
    return encode(
        Transitions(
            run,
            actor=actor,
            seq=seq,
            obs=obs,
            act=act,
            rew=np.zeros(n, np.float32),
            next_obs=obs,
            done=np.zeros(n, np.float32),
            collisions=np.zeros(n, np.int32),
            policy_version=0,
        )
    )


def model(config: dict, streams: list[Stream]):
    """The counts the counter must hold: the unique transitions of every stream."""
    cfg = make_config(config)
    explorer = build_exploration(cfg, task_spec_for(cfg))
    for s in streams:
        explorer.observe(s.obs, s.act)
    return explorer


class Counter:
    """The counter process, seen from outside: launch, info, runs, batches, queries, acks
    (the process itself is one of `cluster`'s)."""

    def __init__(self, bus, cluster) -> None:
        self.bus, self.cluster, self.data_dir = bus, cluster, cluster.data
        self.launches = 0
        self.name = ""
        self._lock = threading.Lock()
        self.acks: dict[str, dict[str, int]] = {}
        self.lengths: dict[str, int] = defaultdict(lambda: BASE["episode_len"])  # run -> rows
        self.ack_history: dict[str, list[dict[str, int]]] = defaultdict(list)
        self.ack_attempts: dict[str, int | None] = {}  # run -> the attempt its last ack named
        bus.subscribe(k_ack("*", "c0"), self._on_ack)

    def _on_ack(self, key: str, payload: bytes) -> None:
        msg = decode(payload, Ack)
        with self._lock:
            self.acks[msg.run] = dict(msg.acked)
            self.ack_history[msg.run].append(dict(msg.acked))
            self.ack_attempts[msg.run] = msg.attempt

    def acked(self, run: str) -> dict[str, int]:
        with self._lock:
            return dict(self.acks.get(run, {}))

    def launch(self, snapshot_s: float = 5.0) -> None:
        self.launches += 1
        self.name = f"counter-{self.launches}"
        snapshots = {"MACB_COUNTER_SNAPSHOT_S": str(snapshot_s)}
        self.cluster.service("counter", "c0", name=self.name, env=snapshots)
        wait_for(lambda: (i := self.info()) and i["ready"], 30, what=f"{self.name} ready")

    def kill(self, sig: int = signal.SIGKILL) -> None:
        self.cluster.kill(self.name, sig)

    def alive(self) -> bool:
        return self.cluster.procs[self.name].poll() is None

    def log(self) -> str:
        return self.cluster.log(self.name)

    def info(self) -> dict | None:
        replies = self.bus.get(k_info("counter", "c0"), timeout=1.0)
        return json.loads(replies[0]) if replies else None

    def stats(self, run: str) -> dict:
        info = self.info()
        assert info is not None, "the counter does not answer"
        return info["runs"][run]

    def start_run(self, run: str, **over) -> dict:
        config = {**BASE, **over}
        self.lengths[run] = 1 if config.get("interleave") == "lockstep" else config["episode_len"]
        self.bus.put(k_control("start"), encode(Start(run, config=config, assign=ASSIGN)))
        wait_for(lambda: run in (self.info() or {}).get("runs", {}), 20, what=f"run {run}")
        return config

    def send(self, run: str, actor: str, stream: Stream, seq: int, n: int) -> None:
        """Rows [seq, seq + n) of `stream` as the actor sends them: one batch per episode."""
        length = self.lengths[run]
        assert seq % length == 0 and n % length == 0, (seq, n, length)
        for first in range(seq, seq + n, length):
            self.send_batch(run, actor, stream, first, length)

    def send_batch(self, run: str, actor: str, stream: Stream, seq: int, n: int) -> None:
        """Rows [seq, seq + n) of `stream` as one batch, whatever its length."""
        sl = slice(seq, seq + n)
        payload = transitions(run, actor, seq, stream.obs[sl], stream.act[sl])
        self.bus.put(k_transitions(run, actor), payload)

    def wait_acked(self, run: str, want: dict[str, int], timeout: float = 20) -> None:
        """The counter acks `want` (an actor of the run not in it: at 0, as acked)."""
        want = {a: want.get(a, 0) for a in ASSIGN.actors}
        wait_for(lambda: self.acked(run) == want, timeout, what=f"acks {want}")

    def query(
        self, run: str, obs: np.ndarray, act: np.ndarray, attempt: int | None = None
    ) -> BonusReply | None:
        replies = self.replies(run, obs, act, attempt).ok
        assert len(replies) <= 1
        return decode(replies[0], BonusReply) if replies else None

    def replies(
        self, run: str, obs: np.ndarray, act: np.ndarray, attempt: int | None = None
    ) -> Replies:
        """Every reply and refusal to a query of the run's `attempt`."""
        query = encode(BonusQuery(run, obs=obs, act=act, attempt=attempt))
        return self.bus.collect_all(self.bus.get_async(k_bonus(run), query, timeout=2.0))


@pytest.fixture
def counter(bus, cluster):
    return Counter(bus, cluster)


def test_exactly_once_per_actor_with_duplicates_gaps_and_overlap(counter):
    counter.launch()
    run = "r-once"
    config = counter.start_run(run)  # batches of one episode: 5 rows
    a0, a1 = Stream(1, 25), Stream(2, 10)
    counter.send(run, "a0", a0, 0, 5)
    counter.send(run, "a0", a0, 5, 5)
    counter.send(run, "a0", a0, 5, 5)  # repeated: 5 duplicates
    counter.wait_acked(run, {"a0": 10})
    answered = len(counter.ack_history[run])
    counter.send(run, "a0", a0, 15, 5)  # out of order: a gap, dropped
    wait_for(lambda: len(counter.ack_history[run]) > answered, 5, what="the gap's ack")
    # Later batches are sent back to back: the counter takes them in bursts (one ack
    # per burst), with the same exactly-once outcome as one by one.
    counter.send(run, "a1", a1, 0, 5)
    counter.send(run, "a0", a0, 10, 5)  # the missing batch
    counter.send(run, "a0", a0, 15, 5)  # the dropped batch, resent
    # Overlaps 18, 19: refused whole, as the learner refuses it (its replay takes whole
    # episodes); the counter took its tail once, rows the learner then never had.
    counter.send_batch(run, "a0", a0, 18, 5)
    counter.send(run, "a0", a0, 20, 5)
    counter.send(run, "a1", a1, 0, 10)  # 5 duplicates, 5 new
    counter.wait_acked(run, {"a0": 25, "a1": 10})

    s = counter.stats(run)
    assert s["counted_transitions"] == 35
    assert s["duplicates"] == 5 + 5
    assert s["gaps"] == 2  # the batch out of order, the overlap
    assert s["acked"] == {"a0": 25, "a1": 10}
    history = [h.get("a0", 0) for h in counter.ack_history[run]]
    assert history == sorted(history), "acks never go back"
    assert history[answered] == 10, "the gap was answered with the expected seq (10)"

    truth = model(config, [a0, a1])
    assert s["table_size"] == len(truth.tables[0])
    obs = np.concatenate([a0.obs, a1.obs])
    act = np.concatenate([a0.act, a1.act])
    reply = counter.query(run, obs, act)
    assert reply is not None and reply.service == "c0"  # (the learner takes its counter's)
    counts = reply.counts
    assert counts.shape == (1, 35) and counts.dtype == np.int64
    assert np.array_equal(counts, np.stack(truth.counts(obs, act)))
    assert counts.min() >= 1
    beta = make_config(config).beta
    np.testing.assert_allclose(reply.bonus[:, 0], beta / np.sqrt(counts[0]), rtol=1e-6)
    assert truth.tables[0].total == 35


def test_a_batch_the_learner_would_refuse_is_not_counted(counter):
    """The counter counts only rows the learner can take into replay: a batch of the
    run's actors, of one episode (one step in lockstep). It counted others, which never
    reached replay, and then took the real rows of those numbers for duplicates, never
    counting them."""
    counter.launch()
    run, steps = "r-refuse", "r-lockstep"
    counter.start_run(run)
    counter.start_run(steps, interleave="lockstep")
    stream = Stream(12, 10)
    assert counter.info()["rejects_total"] == 0
    counter.send_batch(run, "a0", stream, 0, 3)  # not one episode (5 rows)
    counter.send_batch(run, "a9", stream, 0, 5)  # not one of the run's actors
    counter.send_batch(run, "a" * 300, stream, 0, 5)  # no id is that long (255 bytes)
    counter.send_batch(steps, "a0", stream, 0, 5)  # lockstep: a batch is one step
    wait_for(lambda: counter.info()["rejects_total"] == 4, 10, what="4 rejects")
    assert counter.alive()
    info = counter.info()
    assert info["rejects"] == {"transitions": 2, "unknown actor": 2}, info["rejects"]
    log = counter.log()  # (each reason logged once a second at most: the first is)
    assert "transitions: a batch is one episode (5), got 3" in log
    assert info["runs"][run]["counted_transitions"] == 0 and info["runs"][run]["run_rejects"] == 3
    # The actor's own batches for those numbers are all counted.
    counter.send(run, "a0", stream, 0, 10)
    counter.send(steps, "a0", stream, 0, 3)
    counter.wait_acked(run, {"a0": 10})
    counter.wait_acked(steps, {"a0": 3})
    assert counter.stats(run)["counted_transitions"] == 10
    assert counter.stats(steps)["counted_transitions"] == 3


def test_bonus_reply_shapes_for_cen_dis_and_control_arms(counter):
    counter.launch()
    stream, unseen = Stream(3, 10), Stream(4, 3)
    configs = {
        "r-cen": counter.start_run("r-cen"),
        "r-dis": counter.start_run("r-dis", algo="dis-maddpg", explore="dis-macb", beta=0.5),
        "r-none": counter.start_run("r-none", explore="none"),
        "r-const": counter.start_run("r-const", explore="constant", beta=0.3),
    }
    for run in configs:
        counter.send(run, "a0", stream, 0, 10)
    for run in configs:
        counter.wait_acked(run, {"a0": 10})
    obs = np.concatenate([stream.obs, unseen.obs])
    act = np.concatenate([stream.act, unseen.act])
    b = len(obs)

    for run in ("r-cen", "r-dis"):
        truth = model(configs[run], [stream])
        beta = make_config(configs[run]).beta
        reply = counter.query(run, obs, act)
        counts, bonus = reply.counts, reply.bonus
        want = np.stack(truth.counts(obs, act))
        assert counts.shape == (len(truth.tables), b) and bonus.shape == (b, 2)
        assert bonus.dtype == np.float32
        assert np.array_equal(counts, want)
        assert np.all(counts[:, :10] >= 1) and np.all(counts[:, 10:] == 0)
        per_table = beta / np.sqrt(np.maximum(counts, 1))  # never counted: priced as n = 1
        if run == "r-cen":
            np.testing.assert_allclose(bonus[:, 0], bonus[:, 1])  # one bonus for all agents
            np.testing.assert_allclose(bonus[:, 0], per_table[0], rtol=1e-6)
        else:
            np.testing.assert_allclose(bonus, per_table.T, rtol=1e-6)  # each agent its own
        assert counter.stats(run)["uncounted_rows_queried"] == 3

    none = counter.query("r-none", obs, act)
    assert none.counts.shape == (0, b) and np.array_equal(none.bonus, np.zeros((b, 2)))
    const = counter.query("r-const", obs, act)
    assert const.counts.shape == (0, b)
    np.testing.assert_allclose(const.bonus, np.full((b, 2), 0.3, np.float32))
    assert counter.stats("r-none")["counted_transitions"] == 10  # numbered even if not hashed

    # Latency of learner-sized queries (100 rows), as the stats report it.
    big = Stream(5, 100)
    for _ in range(200):
        assert counter.query("r-cen", big.obs, big.act) is not None
    s = counter.stats("r-cen")
    assert s["queries"] == 1 + 200
    assert 0 < s["query_p50_ms"] <= s["query_p99_ms"] < 1000
    print(f"\nbonus query (B=100) p50 {s['query_p50_ms']:.3f} ms, p99 {s['query_p99_ms']:.3f} ms")


def test_sigkill_and_restart_lose_nothing_acknowledged(counter):
    counter.launch(snapshot_s=3600)  # no timed snapshot: the log alone must carry the counts
    run = "r-kill"
    config = counter.start_run(run, episode_len=25)
    n_batches, n = 50, 25
    streams = {"a0": Stream(6, n_batches * n), "a1": Stream(7, n_batches * n)}

    # Phase 1: 10 batches per actor, all acknowledged, then SIGKILL.
    for b in range(10):
        for actor, s in streams.items():
            counter.send(run, actor, s, b * n, n)
    counter.wait_acked(run, {"a0": 250, "a1": 250})
    counter.kill()
    counter.launch(snapshot_s=3600)
    s = counter.stats(run)
    assert s["counted_transitions"] == 500 and s["acked"] == {"a0": 250, "a1": 250}
    assert f"restored run {run}: 500 counted" in counter.log()
    # One record per actor per burst: 2 (all in one burst) to 20 (one batch per burst).
    replayed = int(re.search(r"(\d+) WAL records replayed", counter.log()).group(1))
    assert 2 <= replayed <= 20

    # Phase 2: 40 more batches per actor, paced; SIGKILL while acks are coming in.
    def stream_phase2() -> None:
        for b in range(10, n_batches):
            for actor, st in streams.items():
                counter.send(run, actor, st, b * n, n)
            time.sleep(0.005)

    sender = threading.Thread(target=stream_phase2)
    sender.start()
    wait_for(lambda: counter.acked(run).get("a0", 0) >= 500, 20, what="phase 2 acks")
    counter.kill()
    seen = counter.acked(run)  # what the actors know was acknowledged
    sender.join()
    counter.launch(snapshot_s=3600)
    s = counter.stats(run)
    for actor in streams:
        assert s["acked"][actor] >= seen[actor], "an acknowledged batch was lost"
    assert s["counted_transitions"] == sum(s["acked"].values())
    assert "WAL records replayed" in counter.log()

    # The actors resend everything not acknowledged (from what they saw, so some twice).
    for actor, st in streams.items():
        for seq in range(seen[actor], n_batches * n, n):
            counter.send(run, actor, st, seq, n)
    total = n_batches * n
    counter.wait_acked(run, {"a0": total, "a1": total})
    s = counter.stats(run)
    assert s["counted_transitions"] == 2 * total
    truth = model(config, list(streams.values()))
    obs = np.concatenate([st.obs for st in streams.values()])
    act = np.concatenate([st.act for st in streams.values()])
    reply = counter.query(run, obs, act)
    assert np.array_equal(reply.counts, np.stack(truth.counts(obs, act)))
    assert s["table_size"] == len(truth.tables[0])


def test_garbage_is_dropped_counted_and_harmless(counter):
    counter.launch()
    run = "r-bad"
    counter.start_run(run)
    good = Stream(8, 20)
    counter.send(run, "a0", good, 0, 10)
    counter.wait_acked(run, {"a0": 10})
    before = counter.info()["rejects_total"]
    key = k_transitions(run, "a0")
    ok = transitions(run, "a0", 10, good.obs[10:15], good.act[10:15])

    counter.bus.put(key, b"\x00\xffnot msgpack at all")
    future = msgpack.unpackb(ok, raw=False)
    future["v"] = SCHEMA_VERSION + 1
    counter.bus.put(key, msgpack.packb(future, use_bin_type=True))
    counter.bus.put(
        k_transitions("nope", "a0"), transitions("nope", "a0", 10, good.obs[:5], good.act[:5])
    )
    wide = np.zeros((5, OBS - 1), np.float32)
    counter.bus.put(key, transitions(run, "a0", 10, wide, good.act[:5]))  # wrong dims
    nan = good.obs[10:15].copy()
    nan[0, 0] = np.nan
    counter.bus.put(key, transitions(run, "a0", 10, nan, good.act[10:15]))  # non-finite
    counter.bus.put(k_transitions(run, "a1"), ok)  # key names a1, message a0
    counter.bus.put(k_transitions("r-other", "a0"), ok)  # key and message runs differ
    start = msgpack.unpackb(encode(Start("r-x", config=BASE, assign=ASSIGN)), raw=False)
    start["assign"]["actors"] = "a0"  # an assignment whose actors are not a list
    counter.bus.put(k_control("start"), msgpack.packb(start, use_bin_type=True))
    sent = 8
    # Queries that get no reply: garbage, wrong dims, unknown run.
    assert counter.bus.get(k_bonus(run), b"garbage", timeout=1.0) == []
    assert counter.query(run, wide, good.act[:5]) is None
    assert counter.query("nope", good.obs[:5], good.act[:5]) is None
    sent += 3

    wait_for(lambda: counter.info()["rejects_total"] == before + sent, 10, what=f"{sent} rejects")
    info = counter.info()
    reasons = ("undecodable payload", "unknown run", "actor mismatch", "run mismatch", "start")
    for reason in (*reasons, "schema version"):  # (by the reason's fixed text)
        assert info["rejects"].get(reason, 0) >= 1, (reason, info["rejects"])
    assert counter.alive() and "r-x" not in info["runs"]
    s = info["runs"][run]
    assert s["counted_transitions"] == 10 and s["acked"] == {"a0": 10, "a1": 0}
    # dims, actor mismatch, query dims (the non-finite batch is refused at decode,
    # before its run is looked at: the service's rejects alone)
    assert s["run_rejects"] == 3

    counter.bus.put(key, ok)  # still working
    counter.wait_acked(run, {"a0": 15})
    assert counter.stats(run)["counted_transitions"] == 15


def test_stop_snapshots_and_frees_the_run_and_shutdown_saves_the_rest(counter):
    counter.launch()
    stopped, kept = "r-stop", "r-keep"
    counter.start_run(stopped)
    counter.start_run(kept)
    stream = Stream(9, 10)
    statuses: list[Status] = []
    counter.bus.subscribe(k_status(stopped, "c0"), lambda k, p: statuses.append(decode(p, Status)))
    for run in (stopped, kept):
        counter.send(run, "a0", stream, 0, 10)
    for run in (stopped, kept):
        counter.wait_acked(run, {"a0": 10})

    counter.bus.put(k_control("stop"), encode(Stop(stopped, reason="test over")))
    wait_for(lambda: stopped not in counter.info()["runs"], 10, what="run freed")
    path = counter.data_dir / "counter" / stopped
    assert (path / "stopped").exists()
    snap = torch.load(path / "snapshot.pt", weights_only=True)
    assert snap["expected"] == {"a0": 10, "a1": 0}
    assert int(snap["tables"]["table0"]["counts"].sum()) == 10
    wait_for(lambda: any(m.state == "stopped" for m in statuses), 5, what="stopped status")
    assert counter.query(stopped, stream.obs, stream.act) is None  # no longer served
    assert kept in counter.info()["runs"]

    # SIGTERM: the kept run is snapshotted (log emptied); a restart resumes only that one.
    counter.kill(signal.SIGTERM)
    counter.launch()
    info = counter.info()
    assert list(info["runs"]) == [kept]
    assert info["runs"][kept]["counted_transitions"] == 10
    assert f"restored run {kept}: 10 counted, 10 keys, 0 WAL records replayed" in counter.log()

    # Starting the stopped run's id again starts it afresh; the old state is archived.
    counter.start_run(stopped)
    assert counter.stats(stopped)["counted_transitions"] == 0
    archive = counter.data_dir / "counter" / ".archive"
    assert len(list(archive.iterdir())) == 1

    # A start for the restored run is a new attempt of it (queued again after the first
    # ended while this counter was down): fresh tables and expected numbers, the old
    # state archived, and the new attempt's transitions, numbered from 0, all counted.
    counter.bus.put(k_control("start"), encode(Start(kept, config=BASE, assign=ASSIGN)))
    # (between archiving the old state and opening the new one the run is briefly absent)
    wait_for(
        lambda: (
            (counter.info() or {}).get("runs", {}).get(kept, {}).get("counted_transitions") == 0
        ),
        10,
        what="a new attempt",
    )
    assert len(list(archive.iterdir())) == 2
    assert "started again while restored from disk" in counter.log()
    counter.send(kept, "a0", stream, 0, 10)
    wait_for(lambda: counter.stats(kept)["counted_transitions"] == 10, 10, what="counted anew")
    # A run started by this process takes a repeated start as a no-op.
    counter.bus.put(k_control("start"), encode(Start(kept, config=BASE, assign=ASSIGN)))
    time.sleep(0.5)
    assert counter.stats(kept)["counted_transitions"] == 10


def test_a_retry_whose_stop_never_came_is_counted_afresh_and_freed_by_its_learner(counter):
    """A retry may get the counter while it still serves the old attempt (its stop lost,
    a router restarted): the start names attempt 2, so the counter ends attempt 1 (its
    end stamped 1), counts attempt 2 from nothing, and frees the run on attempt 2's
    learner's "completed", not on a late one of attempt 1."""
    counter.launch()
    run, stream = "r-retry", Stream(11, 10)
    statuses: list[Status] = []
    counter.bus.subscribe(k_status(run, "c0"), lambda k, p: statuses.append(decode(p, Status)))
    start = Start(run, config=BASE, assign=ASSIGN, attempt=1)
    counter.bus.put(k_control("start"), encode(start))
    wait_for(lambda: run in (counter.info() or {}).get("runs", {}), 20, what="attempt 1")
    counter.send(run, "a0", stream, 0, 10)
    counter.wait_acked(run, {"a0": 10})
    assert counter.ack_attempts[run] == 1  # (a reader of another attempt drops them)
    again = Start(run, config=BASE, assign=ASSIGN, attempt=2)
    counter.bus.put(k_control("start"), encode(again))
    wait_for(
        lambda: any((m.state, m.attempt) == ("running", 2) for m in statuses), 10, what="attempt 2"
    )
    ended = next(m for m in statuses if m.state == "stopped")
    assert (ended.attempt, ended.reason) == (1, "attempt 2 of the run started")
    assert counter.stats(run)["counted_transitions"] == 0
    assert len(list((counter.data_dir / "counter" / ".archive").iterdir())) == 1
    counter.send(run, "a0", stream, 0, 5)  # numbered from 0 again
    wait_for(lambda: counter.stats(run)["counted_transitions"] == 5, 10, what="counted anew")
    counter.wait_acked(run, {"a0": 5})
    assert counter.ack_attempts[run] == 2

    def learner(state: str, attempt: int) -> None:
        msg = Status(run, service="L", state=state, detail={}, attempt=attempt)
        counter.bus.put(k_status(run, "L"), encode(msg))

    # The old attempt's learner, late; then garbage on the same key, which the counter
    # counts as a reject: once counted, the status before it (one subscription, in
    # order) has been handled, and the run must still be served.
    before = counter.info()["rejects_total"]
    learner("completed", 1)
    counter.bus.put(k_status(run, "L"), b"\x00garbage")
    wait_for(lambda: counter.info()["rejects_total"] > before, 10, what="the garbage rejected")
    assert run in counter.info()["runs"] and not any(m.state == "completed" for m in statuses)
    learner("completed", 2)
    done = wait_for(
        lambda: next((m for m in statuses if m.state == "completed"), None), 10, what="freed"
    )
    assert done.attempt == 2 and run not in counter.info()["runs"]


def test_a_restored_run_started_again_as_the_attempt_it_holds_keeps_its_counts(counter):
    """A start naming the attempt a restored counter noted (attempt.json) is a repeated
    start of that attempt: its tables stay; one naming no attempt is a new attempt.
    Restored, it prices only that attempt's queries (its learner goes on after the
    counter's restart, and no start comes): another attempt's (a retry, its start lost
    to this counter, or given to another counter) gets a refusal, not stale counts."""
    counter.launch()
    run, stream = "r-same", Stream(3, 10)
    counter.bus.put(k_control("start"), encode(Start(run, config=BASE, assign=ASSIGN, attempt=3)))
    wait_for(lambda: run in (counter.info() or {}).get("runs", {}), 20, what="attempt 3")
    counter.send(run, "a0", stream, 0, 10)
    counter.wait_acked(run, {"a0": 10})
    counter.kill(signal.SIGTERM)
    counter.acks.pop(run)
    counter.launch()
    assert counter.stats(run)["counted_transitions"] == 10
    # Restored, it acks (every second) the attempt its folder notes: were that attempt
    # over, the learner of the next would drop these acks.
    counter.wait_acked(run, {"a0": 10})
    assert counter.ack_attempts[run] == 3
    reply = counter.query(run, stream.obs, stream.act, attempt=3)
    assert reply is not None and reply.service == "c0" and reply.counts.min() == 1
    assert counter.query(run, stream.obs, stream.act) is not None  # (an older learner's)
    other = counter.replies(run, stream.obs, stream.act, attempt=4)
    assert other.ok == [] and [r.by for r in other.refused] == ["c0"], other
    assert "another attempt: asked for attempt 4, holds 3" in other.refused[0].reason
    counter.bus.put(k_control("start"), encode(Start(run, config=BASE, assign=ASSIGN, attempt=3)))
    wait_for(lambda: "attempt 3 started again: already restored" in counter.log(), 10,
             what="the repeated start")  # fmt: skip
    assert counter.stats(run)["counted_transitions"] == 10
    assert "started again while restored from disk" not in counter.log()
    counter.bus.put(k_control("start"), encode(Start(run, config=BASE, assign=ASSIGN)))
    wait_for(lambda: "started again while restored from disk" in counter.log(), 10,
             what="a new attempt")  # fmt: skip
    wait_for(
        lambda: (counter.info() or {}).get("runs", {}).get(run, {}).get("counted_transitions") == 0,
        10,
        what="counted afresh",
    )


def test_timed_snapshots_wait_for_the_log_to_reach_a_quarter_of_the_table(counter):
    # k=64: 16-byte keys, 24 snapshot bytes per key, 16 log bytes per row (+30 per record);
    # episodes of 50 rows, one batch each.
    counter.launch(snapshot_s=0.2)
    run = "r-snap"
    counter.start_run(run, episode_len=50)
    stream = Stream(10, 350)
    counter.send(run, "a0", stream, 0, 200)  # log >= 3,230 B >= 0.25 * 200 * 24 = 1,200
    counter.wait_acked(run, {"a0": 200})
    # (four batches may be taken in more than one burst, and snapshotted in steps)
    wait_for(
        lambda: (s := counter.stats(run))["snapshots"] >= 1 and s["wal_records"] == 0,
        10,
        what="the first rows snapshotted",
    )
    first = counter.stats(run)["snapshots"]
    counter.send(run, "a0", stream, 200, 50)  # log 830 B < 0.25 * 250 * 24 = 1,500
    counter.wait_acked(run, {"a0": 250})
    time.sleep(1.0)  # five timed checks
    s = counter.stats(run)
    assert s["snapshots"] == first and s["wal_records"] == 1, s
    counter.send(run, "a0", stream, 250, 100)  # log >= 2,460 B >= 0.25 * 350 * 24 = 2,100
    counter.wait_acked(run, {"a0": 350})
    wait_for(lambda: counter.stats(run)["snapshots"] == first + 1, 10, what="the next snapshot")
    assert counter.stats(run)["wal_records"] == 0


def test_wal_round_trip_and_torn_tail(tmp_path):
    path = tmp_path / "wal.bin"
    wal = WriteAheadLog(path)
    keys = [np.arange(12, dtype=np.uint8).reshape(3, 4), np.ones((3, 2), np.uint8)]
    wal.append("a0", 0, 3, keys)
    wal.append("a1", 5, 1, [np.zeros((1, 4), np.uint8), np.zeros((1, 2), np.uint8)])
    wal.append("a0", 3, 2, [])  # a run without tables logs only the numbers
    wal.close()
    records, valid, torn = read_wal(path)
    assert not torn and valid == path.stat().st_size
    assert [(r.actor, r.seq, r.n, len(r.keys)) for r in records] == [
        ("a0", 0, 3, 2),
        ("a1", 5, 1, 2),
        ("a0", 3, 2, 0),
    ]
    assert np.array_equal(records[0].keys[0], keys[0])

    with open(path, "ab") as f:  # a kill in the middle of a record
        f.write(b"\x40\x00\x00\x00\x01\x02\x03")
    wal, records = WriteAheadLog.open(path)
    assert len(records) == 3 and path.stat().st_size == valid, "the torn tail is cut"
    wal.append("a1", 6, 1, [np.zeros((1, 4), np.uint8), np.zeros((1, 2), np.uint8)])
    wal.truncate()
    wal.append("a0", 5, 1, [])
    wal.close()
    assert [(r.actor, r.seq) for r in read_wal(path)[0]] == [("a0", 5)]

    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF  # a flipped bit: the CRC refuses the record
    path.write_bytes(bytes(data))
    assert read_wal(path)[0] == [] and read_wal(path)[2]


def test_sigusr1_logs_every_threads_stack_and_the_service_goes_on(counter):
    """A service that seems stuck says where: SIGUSR1 writes its threads' stacks to its
    log (stderr), and it goes on answering and counting."""
    counter.launch()
    os.kill(counter.cluster.pid(counter.name), signal.SIGUSR1)
    wait_for(lambda: "in serve_forever" in counter.log(), 10, what="the stacks in the log")
    assert "Current thread" in counter.log() or "Thread 0x" in counter.log()
    run, stream = "r-usr1", Stream(4, 10)
    counter.start_run(run)
    counter.send(run, "a0", stream, 0, 10)
    counter.wait_acked(run, {"a0": 10})
    assert counter.alive()
    counter.kill(signal.SIGTERM)  # and shuts down as ever, flushing
    assert "1 run(s) saved" in counter.log()


def test_a_shutdown_that_hangs_writes_the_stacks_before_it_is_killed(tmp_path):
    """SIGTERM starts a watchdog: a service whose shutdown does not end writes every
    thread's stack, so the SIGKILL that follows does not hide where it hung."""
    script = tmp_path / "hung.py"
    script.write_text(
        "import logging, queue, threading, time\n"
        "import services.common as common\n"
        "common.SHUTDOWN_STACKS_AFTER_S = 0.5\n"
        "class Hung:\n"
        "    log = logging.getLogger('hung')\n"
        "    stop_event = threading.Event()\n"
        "    inbox = queue.SimpleQueue()\n"
        "def flush_forever():\n"
        "    while True:\n"
        "        time.sleep(0.05)\n"
        "service = Hung()\n"
        "common.stop_on_signals(service)\n"
        "print('ready', flush=True)\n"
        "service.stop_event.wait()\n"
        "flush_forever()\n"
    )
    proc = subprocess.Popen(
        [sys.executable, str(script)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        proc.send_signal(signal.SIGTERM)
        time.sleep(2.0)
        assert proc.poll() is None  # still hung: the watchdog does not end it
    finally:
        proc.kill()
        _, err = proc.communicate(timeout=10)
    assert "in flush_forever" in err, err
