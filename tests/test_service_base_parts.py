"""The parts every service shares, in process, no bus: the runs served and the starts
taken (`services/runs.py`), the runs file a restart rejoins from, peers away and their
grace (`services/peers.py`), the inbox's bursts and the rejects tally (`services/inbox.py`)."""

from __future__ import annotations

import json
import logging
import queue
import threading
import time

import msgpack
import pytest

from services.common import ServiceBase
from services.inbox import DRAINED, MAX_REASONS, OTHER_REASONS, Inbox, Rejects
from services.peers import CHECK_S, PeerWatch, live_peer
from services.runs import ServedRuns
from shared.config import make_config
from shared.net.messages import Assignment, Stop, Transitions
from shared.net.wire import SCHEMA_VERSION, WireError, decode, encode

LOG = logging.getLogger("test")
RAW = {"task": "speaker_listener", "explore": "dis-macb", "k": 32}


def assignment(**fields) -> Assignment:
    """An assignment of learner L and actor a0, with `fields` on top."""
    return Assignment.from_wire({"learner": "L", "actors": ["a0"], **fields})


# ------------------------------------------------------------ runs served, starts taken
def test_a_service_is_assigned_by_its_role_or_in_its_roles_list():
    assign = assignment(actors=["a0", "a1"], counter="c0")
    assert assign.names("learner", "L") and not assign.names("learner", "L2")
    assert assign.names("actor", "a1") and not assign.names("actor", "a2")
    assert not assign.names("evaluator", "e")


def test_a_service_serving_a_group_takes_its_other_runs_and_nothing_else():
    served = ServedRuns(1, None, LOG)
    group = assignment(group=["g1", "g2"])
    assert not served.full() and not served.joins_group("g2", group)  # free: not a join
    served.join("g1", make_config(RAW), group, RAW)
    assert served.full()
    assert served.joins_group("g2", group)
    assert not served.joins_group("g3", group)  # not one of the group's runs
    assert not served.joins_group("g2", assignment(group=["g1", "g2", "g4"]))
    assert not served.joins_group("x", assignment())


def test_messages_are_for_a_served_run_and_a_run_let_go_is_dropped_silently():
    served = ServedRuns(2, None, LOG)
    served.join("r", make_config(RAW), assignment(), RAW)
    assert served.refusal("r", "r") is None
    assert served.refusal("r", "other").startswith("run mismatch")
    assert served.refusal(None, "r").startswith("run mismatch")
    assert served.refusal("x", "x") == "unknown run: x"
    served.leave("r")
    assert list(served.finished) == ["r"] and not served.active
    assert served.refusal("r", "r") == ""  # late traffic of a finished run
    served.leave("never-served")
    assert list(served.finished) == ["r"]


def test_the_runs_file_holds_the_runs_served_in_order_and_brings_them_back(tmp_path):
    path = tmp_path / "services" / "s.json"
    served = ServedRuns(2, path, LOG)
    raw2 = {**RAW, "k": 16}
    group = assignment(group=["g1", "g2"])
    served.join("g1", make_config(RAW), group, RAW)
    served.join("g2", make_config(raw2), group, raw2)
    served.save()
    back = ServedRuns(2, path, LOG).saved()
    assert [(s.run, s.config.k, s.raw, s.assign) for s in back] == [
        ("g1", 32, RAW, group),
        ("g2", 16, raw2, group),
    ]
    on_file = {"learner": "L", "actors": ["a0"], "group": ["g1", "g2"]}  # the map a Start holds
    assert [e["assign"] for e in json.loads(path.read_text())["runs"]] == [on_file, on_file]
    served.leave("g1")
    served.leave("g2")
    served.save()
    assert not path.exists() and ServedRuns(2, path, LOG).saved() == []


def test_a_runs_file_of_one_run_still_loads_and_a_bad_one_is_refused_aside(tmp_path):
    path = tmp_path / "s.json"
    assign = {"counter": "c0", "learner": "L", "evaluator": "e", "actors": ["a0"]}
    path.write_text(json.dumps({"run": "r", "config": RAW, "assign": assign}))
    back = ServedRuns(1, path, LOG).saved()
    assert [s.run for s in back] == ["r"] and [s.assign.to_wire() for s in back] == [assign]
    no_actors = {"runs": [{"run": "r", "config": RAW, "assign": {"learner": "L"}}]}
    # a run id no start could name (refused at the start): the learner would build its
    # folder from it, outside its data dir
    climbs = {"runs": [{"run": "../../r", "config": RAW, "assign": assign}]}
    for bad in (
        "not json",
        json.dumps({"runs": []}),
        json.dumps({"runs": [{"run": "r"}]}),
        json.dumps(no_actors),
        json.dumps(climbs),
    ):
        path.write_text(bad)
        assert ServedRuns(1, path, LOG).saved() == []
        assert not path.exists() and path.with_name("s.json.refused").read_text() == bad


def test_a_service_that_restores_its_own_runs_writes_no_runs_file(tmp_path):
    served = ServedRuns(5, None, LOG)
    served.join("r", make_config(RAW), assignment(), RAW)
    served.save()
    assert served.saved() == [] and list(tmp_path.iterdir()) == []


# ------------------------------------------------------------ peers
def test_a_peer_away_is_given_its_grace_and_one_back_is_forgiven():
    assert live_peer("macb/live/actor/a0") == ("actor", "a0")
    assert live_peer("macb/live/actor") is None
    peers = PeerWatch(grace_s=10.0)
    assert peers.seen("macb/other", False, 0.0) is None
    assert peers.seen("macb/live/learner/L", False, 0.0) == ("learner", "L", False)
    assert peers.seen("macb/live/actor/a0", False, 1.0) == ("actor", "a0", False)
    assert peers.given_up(9.0) == []
    assert peers.seen("macb/live/actor/a0", True, 9.5).back  # back within its grace
    assert not peers.seen("macb/live/actor/a0", True, 9.6).back  # already back
    assert peers.given_up(10.0) == [("learner", "L")]  # given up: forgotten
    assert peers.given_up(30.0) == []


def test_peers_away_are_looked_at_no_more_than_every_check_interval():
    peers = PeerWatch(grace_s=0.0)
    peers.seen("macb/live/actor/a0", False, 100.0)
    assert peers.given_up(100.0) == [("actor", "a0")]
    peers.seen("macb/live/actor/a1", False, 100.0)
    assert peers.given_up(100.0 + CHECK_S / 2) == []  # too soon after the last look
    assert peers.given_up(100.0 + CHECK_S * 2) == [("actor", "a1")]
    peers.seen("macb/live/actor/a2", False, 200.0)
    peers.clear()
    assert peers.given_up(300.0) == []


# ------------------------------------------------------------ inbox and rejects
def test_the_inbox_says_once_when_a_burst_has_drained_and_waits_only_when_idle():
    q: queue.SimpleQueue = queue.SimpleQueue()
    inbox = Inbox(q)
    t0 = time.monotonic()
    assert inbox.take(busy=False, wait_s=0.05) is None  # idle: waits for a message
    assert time.monotonic() - t0 >= 0.04
    # (waits of 60 s where none is due: a stall of a loaded machine is not mistaken for one)
    t0 = time.monotonic()
    assert inbox.take(busy=True, wait_s=60.0) is None  # work waiting: no wait
    assert time.monotonic() - t0 < 30
    q.put(("t", "k1", b"1"))
    q.put(("t", "k2", b"2"))
    assert inbox.take(False, 60.0) == ("t", "k1", b"1")
    assert inbox.take(False, 60.0) == ("t", "k2", b"2")
    t0 = time.monotonic()
    assert inbox.take(False, 60.0) == DRAINED  # in a burst: not kept waiting
    assert time.monotonic() - t0 < 30
    assert inbox.take(False, 0.01) is None  # once


SIGNAL_IN_A_WAIT = """
import logging, queue, signal, sys, threading, time
from services.common import stop_on_signals
from services.inbox import Inbox

class SlowHandler(logging.Handler):
    def emit(self, record):  # a log line that outlasts the wait's timeout (a loaded host)
        t = time.monotonic()
        while time.monotonic() - t < 0.2:
            pass

class Service:
    log = logging.getLogger("slow")
    stop_event = threading.Event()
    inbox = getattr(queue, sys.argv[1])()

Service.log.addHandler(SlowHandler())
Service.log.setLevel(logging.INFO)
stop_on_signals(Service)
inbox = Inbox(Service.inbox)
main = threading.main_thread().ident  # (the thread in the wait gets the signal)
threading.Timer(0.02, lambda: signal.pthread_kill(main, signal.SIGTERM)).start()
t0 = time.monotonic()
while not Service.stop_event.is_set():
    assert inbox.take(False, 0.05) is None
print(f"stopped after {time.monotonic() - t0:.2f} s")
"""


@pytest.mark.parametrize("inbox", ["SimpleQueue", "Queue"])
def test_a_stop_signal_in_the_inboxs_wait_ends_the_loop(inbox):
    """SIGTERM while the service thread waits on its inbox: CPython 3.11's SimpleQueue
    (the counter's) waited on with no timeout once the handler outlasted the wait's, and
    the loop never saw its stop (a counter alive 20 s after SIGTERM). The handler wakes it."""
    import subprocess
    import sys

    from tests.harness import ROOT

    got = subprocess.run(
        [sys.executable, "-c", SIGNAL_IN_A_WAIT, inbox],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert got.returncode == 0 and "stopped after" in got.stdout, got.stderr[-2000:]
    assert float(got.stdout.split()[2]) < 2.0, got.stdout


def test_rejects_are_counted_by_reason_and_logged_at_most_once_an_interval():
    rejects = Rejects(log_every_s=1.0)
    assert rejects.add("unknown run: r1", now=10.0) == 1
    assert rejects.add("unknown run: r2", now=10.5) is None
    assert rejects.add("bad config: k", now=11.2) == 3
    assert rejects.counts() == ({"unknown run": 2, "bad config": 1}, 3)


def test_rejects_from_several_threads_are_all_counted():
    rejects = Rejects()

    def drop() -> None:
        for _ in range(2000):
            rejects.add("x: y", time.monotonic())

    threads = [threading.Thread(target=drop) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert rejects.counts() == ({"x": 8000}, 8000)


def _wire_reason(payload: bytes) -> str:
    """The reason a service drops `payload` with (as a transitions message)."""
    with pytest.raises(WireError) as err:
        decode(payload, Transitions)
    return str(err.value)


@pytest.mark.parametrize(
    "tamper",
    [
        lambda raw, i: raw.update(v=1000 + i),  # a schema version of the sender's choice
        lambda raw, i: raw.update(type=f"t{i}"),  # a message type of its choice
    ],
)
def test_reasons_a_sender_varies_fall_in_one_bucket(tamper):
    """The text before the ':' is fixed: a sender varying what follows it (a version, a
    type, an array's dtype) adds to one count, not a bucket per message in every info
    reply."""
    rejects = Rejects()
    for i in range(300):
        raw = msgpack.unpackb(encode(Stop("r", reason="x")), raw=False)
        tamper(raw, i)
        rejects.add(_wire_reason(msgpack.packb(raw)), now=0.0)
    by_reason, total = rejects.counts()
    assert total == 300 and len(by_reason) == 1, by_reason
    arrays = {"v": SCHEMA_VERSION, "type": "transitions", "run": "r"}
    for i in range(300):
        obs = {"nd": f"<x{i}", "shape": [1], "data": b"\0"}
        rejects.add(_wire_reason(msgpack.packb({**arrays, "obs": obs})), now=0.0)
    assert len(rejects.counts()[0]) == 2 and "bad array encoding" in rejects.counts()[0]


def test_the_tally_keeps_a_bounded_number_of_reasons():
    rejects = Rejects()
    for i in range(10 * MAX_REASONS):
        rejects.add(f"reason {i}: why", now=0.0)
    by_reason, total = rejects.counts()
    assert total == 10 * MAX_REASONS and len(by_reason) == MAX_REASONS
    assert by_reason["reason 0"] == 1 and by_reason[OTHER_REASONS] == 9 * MAX_REASONS + 1
    rejects.add("reason 1: again", now=0.0)  # a bucket kept goes on counting
    assert rejects.counts()[0]["reason 1"] == 2
    rejects = Rejects()
    rejects.add("x" * 10_000, now=0.0)  # a long reason: its bucket is cut short
    assert [len(b) for b in rejects.counts()[0]] == [80]


class Raising(ServiceBase):
    """A service whose handler raises what its message makes it raise."""

    role = "test"

    def handle(self, tag: str, key: str, payload: bytes) -> None:
        if payload == b"index":
            raise IndexError("list index out of range")
        if payload == b"disk":
            raise OSError(28, "No space left on device")
        raise ValueError(f"cannot read {payload!r}")


def bare_service() -> Raising:
    """Only what dispatching a message uses: no bus."""
    svc = Raising.__new__(Raising)
    svc.log = logging.getLogger("test.raising")
    svc.reject_tally = Rejects(log_every_s=0.0)
    svc._traced, svc._traced_lock = set(), threading.Lock()
    return svc


def test_a_handler_that_raises_drops_the_message_counts_it_and_the_service_goes_on(caplog):
    svc = bare_service()
    with caplog.at_level(logging.WARNING, logger="test.raising"):
        for i in range(3):
            svc._dispatch("transitions", f"macb/run/r/transitions/a{i}", b"%d" % i)
        svc._dispatch("transitions", "macb/run/r/transitions/a0", b"index")
    by_reason, total = svc.reject_tally.counts()
    assert by_reason == {"handler raised ValueError": 3, "handler raised IndexError": 1}
    assert total == 4
    traced = [r for r in caplog.records if r.exc_info is not None]
    assert [r.exc_info[0] for r in traced] == [ValueError, IndexError]  # once each
    assert "macb/run/r/transitions/a0" in traced[0].getMessage()
    dropped = [r.getMessage() for r in caplog.records if r.exc_info is None]
    assert len(dropped) == 4 and "handler raised ValueError: cannot read b'1'" in dropped[1]


def test_the_services_own_failures_still_end_it_for_its_restart():
    """A disk error while handling a message (a log that cannot be written) is the
    service's failure, not the message's: it ends the process, whose restart goes on
    from its files, rather than being counted as a dropped message."""
    svc = bare_service()
    with pytest.raises(OSError):
        svc._dispatch("transitions", "macb/run/r/transitions/a0", b"disk")
    assert svc.reject_tally.counts() == ({}, 0)
