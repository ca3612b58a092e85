"""A service's own declarations and the starts it takes, in process on a real router:
the handlers are called directly (no inbox, no thread), so what a start or a stop
leaves behind is read off the service itself.

- A start naming a run id that is no safe name (`../../x`, a slash, too long) is
  refused, counted and logged by every service before any folder or key is built from
  it: the learner wiped and created `data_dir/learner/<run>`, outside its data dir.
- A run's publishers (the learner's weights, eval weights, acks and lockstep answers;
  an actor's transitions and act requests) are undeclared when the run is let go, as
  its subscriptions are: each holds state in the session, and a long-lived service
  otherwise grew by a few per run until it closed.
- An ack of another attempt of the run is dropped and counted: a counter that restored
  an ended attempt from disk acks that attempt's positions every second, and the new
  attempt's learner took them (acks only move forward) and released batches into
  replay that its counter had not counted.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
import torch

from services.actor.main import ActorService
from services.common import ServiceBase
from services.learner.main import LearnerService
from shared.config import make_config
from shared.net import bus as keys
from shared.net.bus import Bus
from shared.net.messages import Ack, Assignment, Start, Stop, Transitions, run_id_error
from shared.net.wire import encode

CONFIG = {
    "task": "speaker_listener",
    "explore": "none",
    "episodes": 4,
    "episode_len": 5,
    "hidden": [16, 16],
    "learner_lanes": 1,
}
ASSIGN = Assignment(learner="L", actors=("a0",), counter="c0", evaluator="e0")


@pytest.fixture(autouse=True)
def _torch_threads():
    """Services set torch's threads for their process: this one's is restored."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def control(svc: ServiceBase, msg: Start | Stop) -> None:
    """`msg` as the service's control subscription hands it over."""
    action = "start" if isinstance(msg, Start) else "stop"
    svc._on_control(action, keys.k_control(action), encode(msg))


@pytest.mark.parametrize(
    "run", ["ok-1", "x20250101-120000-abcdef-3", "_r.2", "r" * 128], ids=lambda r: r[:12]
)
def test_a_run_id_is_a_safe_name(run):
    assert run_id_error(run) is None


@pytest.mark.parametrize("run", ["../../escape", "a/b", "", ".hidden", "-r", "r*", "r" * 129])
def test_an_unsafe_run_id_is_named_as_such(run):
    assert run_id_error(run) is not None


def test_a_start_naming_an_unsafe_run_id_is_refused_and_builds_no_path(router, tmp_path):
    outside = tmp_path / "escape"  # data_dir/learner/../../escape
    outside.mkdir()
    (outside / "checkpoint.pt").write_bytes(b"someone else's")
    svc = LearnerService("L", [router], tmp_path / "data")
    try:
        for run in ("../../escape", "a/b"):
            control(svc, Start(run, config=CONFIG, assign=ASSIGN, attempt=1))
        assert not svc.active
        assert (outside / "checkpoint.pt").read_bytes() == b"someone else's"  # not wiped
        assert not (tmp_path / "data" / "learner").exists()
        assert svc.rejects == {"run id": 2}, svc.rejects  # (one reason, whatever the ids)
        control(svc, Start("fine", config=CONFIG, assign=ASSIGN, attempt=1))  # still serving
        assert list(svc.active) == ["fine"] and (tmp_path / "data" / "learner" / "fine").is_dir()
    finally:
        svc.shutdown()


def test_a_publisher_is_undeclared_before_the_session_closes(router):
    bus = Bus([router])
    try:
        held = len(bus._held)
        pub = bus.publisher("macb/test/publisher")
        pub(b"x")
        assert len(bus._held) == held + 1
        pub.undeclare()
        pub.undeclare()  # (once only)
        bus.undeclare(pub)
        assert len(bus._held) == held
    finally:
        bus.close()


@pytest.mark.parametrize(
    ("role", "interleave"),
    [("learner", "async"), ("learner", "lockstep"), ("actor", "async"), ("actor", "lockstep")],
)
def test_a_runs_publishers_go_with_the_run(router, tmp_path, role, interleave):
    cls = LearnerService if role == "learner" else ActorService
    svc = cls("L" if role == "learner" else "a0", [router], tmp_path / "data")
    try:
        held = len(svc.bus._held)
        for attempt in (1, 2):  # (one run after another: nothing piles up)
            config = {**CONFIG, "interleave": interleave}
            control(svc, Start("r", config=config, assign=ASSIGN, attempt=attempt))
            assert svc.serves("r"), svc.rejects
            declared = len(svc.bus._held) - held
            assert declared >= 3, "the run's subscriptions and publishers"
            control(svc, Stop("r", reason="the test is over"))
            assert not svc.active
            assert len(svc.bus._held) == held, "the run's declarations outlived it"
    finally:
        svc.shutdown()


def test_an_ack_of_another_attempt_is_dropped_and_counted(router, tmp_path):
    """The learner of attempt 2 holds a batch its counter has not counted; the counter
    that restored attempt 1 acks past it. That ack releases nothing; attempt 2's does."""
    svc = LearnerService("L", [router], tmp_path / "data")
    try:
        control(svc, Start("r", config={**CONFIG, "explore": "cen-macb"}, assign=ASSIGN,
                           attempt=2))  # fmt: skip
        st = svc.runs["r"]
        n, obs_dim, act_dim = 5, st.spec.joint_obs_dim, st.spec.joint_act_dim
        obs = np.zeros((n, obs_dim), np.float32)
        batch = Transitions("r", "a0", 0, obs=obs, act=np.zeros((n, act_dim), np.float32),
                            rew=np.zeros(n, np.float32), next_obs=obs,
                            done=np.zeros(n, np.float32), collisions=np.zeros(n, np.int32),
                            policy_version=0)  # fmt: skip
        svc.handle("transitions", keys.k_transitions("r", "a0"), encode(batch))
        assert len(st.intake.held["a0"]) == 1 and st.intake.ingested == 0

        def counter_acks(attempt: int | None) -> None:
            ack = Ack("r", service="c0", acked={"a0": 20}, window=0, attempt=attempt)
            svc.handle("ack", keys.k_ack("r", "c0"), encode(ack))

        counter_acks(1)
        assert len(st.intake.held["a0"]) == 1 and st.intake.ingested == 0, "released"
        assert svc.rejects.get("ack of another attempt") == 1, svc.rejects
        counter_acks(2)
        assert not st.intake.held["a0"] and st.intake.ingested == n
    finally:
        svc.shutdown()


def test_an_ack_naming_no_attempt_is_taken_as_an_older_peers(router, tmp_path):
    svc = ServiceBase("s", [router], tmp_path)
    try:
        svc.served.join("r", make_config(CONFIG), ASSIGN, CONFIG, 2)
        key = keys.k_ack("r", "c0")
        acks = {
            a: Ack("r", service="c0", acked={"a0": 5}, window=0, attempt=a) for a in (1, 2, None)
        }
        assert svc.decode_for_run(key, encode(acks[1]), Ack) is None
        assert svc.decode_for_run(key, encode(acks[2]), Ack) == acks[2]
        assert svc.decode_for_run(key, encode(acks[None]), Ack) == acks[None]
        assert svc.rejects == {"ack of another attempt": 1}
    finally:
        svc.shutdown()


def test_a_query_whose_handler_raises_is_refused_counted_and_the_service_answers_on(
    router, tmp_path, caplog
):
    """A queryable's handler runs on Zenoh's thread, out of the dispatch loop's reach: its
    exception is the query's refusal naming the exception's type (the asker does not wait
    out its timeout), a counted reject, and one logged traceback; the next query is
    answered."""
    svc = ServiceBase("s", [router], tmp_path)
    bus = Bus([router])

    def handler(key: str, payload: bytes) -> bytes:
        if payload == b"bad":
            raise KeyError("no such table")
        return b"ok:" + payload

    try:
        svc.answer("macb/test/q/s", handler)
        # The queryable's declaration reaches the router a moment after answer() returns; a
        # query sent before then finds no one (neither answer nor refusal), so wait for it.
        deadline = time.monotonic() + 10
        while bus.get("macb/test/q/s", b"ready", timeout=1) != [b"ok:ready"]:
            assert time.monotonic() < deadline, "the queryable never became reachable"
            time.sleep(0.05)
        with caplog.at_level(logging.ERROR, logger="macb.service.s"):
            for _ in range(3):
                got = Bus.collect_all(bus.get_async("macb/test/q/s", b"bad", timeout=5))
                assert got.ok == [] and [(r.by, r.reason) for r in got.refused] == [
                    ("s", "handler raised KeyError")
                ]
        assert svc.rejects == {"handler raised KeyError": 3}
        assert len([r for r in caplog.records if r.exc_info]) == 1  # its traceback once
        assert bus.get("macb/test/q/s", b"fine", timeout=5) == [b"ok:fine"]
    finally:
        bus.close()
        svc.shutdown()
