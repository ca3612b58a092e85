"""The exactly-once rule and the run-status rule, in process (shared/net/protocol.py).

Like Tianshou's buffer tests, these assert invariants over many deliveries rather than
single outcomes: whatever the channel does (duplicates, loss, reordering, restarts of
either side), every transition is taken exactly once and in order.
"""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.net.messages import Assignment
from shared.net.monitor import run_verdict
from shared.net.protocol import (
    AckTracker,
    Arrival,
    Decision,
    ReceiveCursor,
    Sender,
    decide,
)


# --------------------------------------------------------------------- the rule
@pytest.mark.parametrize(
    ("expected", "seq", "n", "arrival", "skip", "taken"),
    [
        (0, 0, 20, Arrival.TAKE, 0, 20),
        (40, 40, 20, Arrival.TAKE, 0, 20),
        (40, 20, 20, Arrival.DUPLICATE, 20, 0),  # ends exactly at expected
        (40, 0, 20, Arrival.DUPLICATE, 20, 0),
        (40, 60, 20, Arrival.GAP, 0, 0),
        (40, 41, 20, Arrival.GAP, 0, 0),
        (40, 30, 20, Arrival.OVERLAP, 10, 10),
        (40, 39, 20, Arrival.OVERLAP, 1, 19),
    ],
)
def test_decide_every_case(expected, seq, n, arrival, skip, taken):
    assert decide(expected, seq, n) == Decision(arrival, skip, taken)


def test_cursor_takes_in_order_and_counts_duplicates_and_gaps():
    c = ReceiveCursor()
    assert c.take("a", 0, 20).arrival is Arrival.TAKE
    assert c.take("a", 0, 20).arrival is Arrival.DUPLICATE
    assert c.take("a", 40, 20).arrival is Arrival.GAP
    d = c.take("a", 10, 20)  # overlap: rows 20..29 are new
    assert (d.arrival, d.skip, d.taken) == (Arrival.OVERLAP, 10, 10)
    assert c.take("b", 0, 5).took  # another actor has its own number
    assert c.positions() == {"a": 30, "b": 5}
    assert c.duplicate_rows == 20 + 10
    assert c.gaps == 1


def test_whole_batch_cursor_refuses_an_overlap_without_advancing():
    c = ReceiveCursor(actors=["a"], partial=False)
    c.take("a", 0, 20)
    d = c.take("a", 10, 20)
    assert d.arrival is Arrival.OVERLAP and not d.took
    assert c.expected("a") == 20  # the sender resends from the ack
    assert c.gaps == 1 and c.duplicate_rows == 0


def test_fixed_actors_refuse_strangers():
    c = ReceiveCursor(actors=["a"])
    assert c.knows("a") and not c.knows("x")
    with pytest.raises(KeyError):
        c.take("x", 0, 1)
    with pytest.raises(KeyError):
        ReceiveCursor({"x": 3}, actors=["a"])


def test_staging_copy_leaves_the_original_until_committed():
    c = ReceiveCursor({"a": 20})
    staged = c.copy()
    staged.take("a", 20, 20)
    staged.take("a", 0, 20)
    assert c.positions() == {"a": 20} and c.duplicate_rows == 0
    assert staged.positions() == {"a": 40} and staged.duplicate_rows == 20


def test_restart_from_positions_continues_exactly():
    """A receiver restarted from its saved positions (a snapshot, a checkpoint) takes
    what follows and refuses what it had, as if it had never stopped."""
    before = ReceiveCursor()
    for seq in range(0, 100, 20):
        before.take("a", seq, 20)
    after = ReceiveCursor(before.positions())
    assert after.take("a", 80, 20).arrival is Arrival.DUPLICATE
    assert after.take("a", 100, 20).arrival is Arrival.TAKE


def test_ack_tracker_only_moves_forward_and_ignores_junk():
    t = AckTracker(["a"])
    assert t.ack("a", 40)
    assert not t.ack("a", 20)  # an old ack (a restarted service) does not move it back
    assert not t.ack("a", "40") and not t.ack("a", True) and not t.ack("x", 100)
    assert t["a"] == 40
    assert t.covers("a", 20, 20) and not t.covers("a", 40, 20)


# --------------------------------------------------------------------- invariants
def _deliver(sender_batches, cursor, shuffle, duplicate, drop, rng):
    """Deliver batches through a channel that reorders, duplicates and drops them;
    return the (seq, row) pairs the receiver took, in the order it took them."""
    wire = list(sender_batches)
    if shuffle:
        rng.shuffle(wire)
    out = []
    for seq, n in wire:
        copies = 1 + (rng.random() < duplicate)
        for _ in range(copies):
            if rng.random() < drop:
                continue
            d = cursor.take("a", seq, n)
            out.extend(range(seq + d.skip, seq + n) if d.took else [])
    return out


@settings(max_examples=200, deadline=None)
@given(
    sizes=st.lists(st.integers(1, 25), min_size=1, max_size=30),
    seed=st.integers(0, 2**32 - 1),
    shuffle=st.booleans(),
    duplicate=st.floats(0, 0.5),
    drop=st.floats(0, 0.5),
    partial=st.booleans(),
)
def test_whatever_the_channel_does_every_row_is_taken_once_in_order(
    sizes, seed, shuffle, duplicate, drop, partial
):
    rng = random.Random(seed)
    batches, seq = [], 0
    for n in sizes:
        batches.append((seq, n))
        seq += n
    total = seq
    cursor = ReceiveCursor(partial=partial)
    taken: list[int] = []
    for _ in range(200):  # the sender resends from the ack until everything is in
        start = cursor.expected("a")
        if start >= total:
            break
        pending = [(s, n) for s, n in batches if s + n > start]
        taken += _deliver(pending, cursor, shuffle, duplicate, drop, rng)
    assert taken == list(range(total))  # each row once, in order: no loss, no double
    assert cursor.expected("a") == total


def test_resent_overlapping_batches_are_taken_for_their_new_tail_only():
    """A sender whose batches were re-cut (a restart that numbers differently) overlaps
    what was taken: a partial cursor keeps only the new rows."""
    cursor = ReceiveCursor()
    rows = []
    for seq, n in [(0, 10), (5, 10), (12, 10), (0, 30), (30, 5)]:
        d = cursor.take("a", seq, n)
        rows += list(range(seq + d.skip, seq + n)) if d.took else []
    assert rows == list(range(35))


# --------------------------------------------------------------------- the sender
def test_sender_numbers_keeps_until_every_confirmer_acks_and_resends_when_stuck():
    s = Sender(confirm=("learner", "counter"), credit_from="learner", bounded=("counter",))
    s.on_ack("learner", 0, now=0.0, window=40)
    assert s.can_send(20)
    assert s.send(20, b"b0", now=0.0) == 0
    assert s.send(20, b"b1", now=0.0) == 20
    assert not s.can_send(20)  # the window (40 beyond the learner's ack) is used up
    s.on_ack("learner", 40, now=0.1, window=40)
    assert len(s.unacked) == 2 and not s.settled  # the counter has not confirmed
    assert s.due(now=0.5) == []  # the learner's ack was progress
    assert s.due(now=1.2) == [b"b0", b"b1"] and s.resends == 2
    assert s.due(now=1.3) == []  # the clock restarts at each resend
    s.on_ack("counter", 20, now=1.4)
    assert [p for _, _, p in s.unacked] == [b"b1"]
    s.on_ack("counter", 40, now=1.5)
    assert s.settled


def test_sender_stops_while_a_bounded_service_is_too_far_behind():
    s = Sender(
        confirm=("learner", "counter"),
        credit_from="learner",
        bounded=("counter",),
        max_unconfirmed=2,
    )
    s.on_ack("learner", 0, now=0.0, window=1000)
    s.send(20, b"0", 0.0)
    s.send(20, b"1", 0.0)
    assert not s.can_send(20)  # two batches the counter has not counted
    s.on_ack("counter", 20, now=0.1)
    assert s.can_send(20)


def test_sender_ignores_acks_of_others_and_junk():
    s = Sender(confirm=("learner",), credit_from="learner")
    s.send(20, b"0", 0.0)
    for service, seq in [("someone", 20), ("learner", "20"), ("learner", None)]:
        s.on_ack(service, seq, now=0.1, window=100)
    assert not s.settled and s.window == 0
    s.on_ack("learner", 20, now=0.2, window=100)
    assert s.settled and s.window == 100


def test_sender_and_receiver_over_a_lossy_channel_deliver_exactly_once():
    """The whole protocol: an actor's Sender against a learner-like whole-batch cursor
    and a counter-like partial one, through a channel that loses and repeats messages
    in both directions; the receivers restart from their positions midway."""
    rng = random.Random(7)
    n, episodes = 20, 60
    sender = Sender(
        confirm=("learner", "counter"),
        credit_from="learner",
        bounded=("counter",),
        resend_after_s=1.0,
    )
    learner, counter = ReceiveCursor(actors=["a"], partial=False), ReceiveCursor()
    got = {"learner": [], "counter": []}
    now, sent = 0.0, 0

    def arrive(payload: tuple[int, int]) -> None:
        nonlocal learner, counter
        seq, rows = payload
        for name in ("learner", "counter"):
            if rng.random() < 0.2:
                continue  # lost on the way to this receiver
            cur = learner if name == "learner" else counter
            d = cur.take("a", seq, rows)
            if d.took:
                got[name] += list(range(seq + d.skip, seq + rows))
            if rng.random() > 0.2:  # the ack may be lost too
                window = 2 * n if name == "learner" else None
                sender.on_ack(name, cur.expected("a"), now, window=window)

    sender.on_ack("learner", 0, now, window=2 * n)
    for step in range(5000):
        now += 0.1
        if step == 1500:  # both receivers restart from what they had
            learner = ReceiveCursor(learner.positions(), actors=["a"], partial=False)
            counter = ReceiveCursor(counter.positions())
        for payload in sender.due(now):
            arrive(payload)
        if sent < episodes and sender.can_send(n):
            payload = (sender.seq, n)
            sender.send(n, payload, now)  # type: ignore[arg-type]
            sent += 1
            if rng.random() < 0.1:
                arrive(payload)  # delivered twice
            arrive(payload)
        if sent == episodes and sender.settled:
            break
    assert sender.settled
    assert got["learner"] == got["counter"] == list(range(episodes * n))


# --------------------------------------------------------------------- run status
ASSIGN = Assignment.from_wire({"learner": "L", "evaluator": "E", "counter": "C", "actors": ["A0"]})


def test_run_verdict_running_until_learner_and_evaluator_complete():
    assert run_verdict({}, ASSIGN, 0).state == "running"
    states = {"L": {"state": "completed"}, "E": {"state": "running"}}
    assert run_verdict(states, ASSIGN, 0).state == "running"


def test_run_verdict_waits_for_the_evaluators_last_points():
    states = {
        "L": {"state": "completed"},
        "E": {"state": "completed", "points": 5},
        "C": {"state": "completed", "counted_transitions": 100},
    }
    v = run_verdict(states, ASSIGN, 3)
    assert (v.state, v.points_expected, v.missing) == ("finishing", 5, 2)
    assert not v.counter_pending
    assert run_verdict(states, ASSIGN, 5).state == "completed"


def test_run_verdict_waits_for_the_counters_final_report():
    """The counter reports its final count after its snapshot, which can come after
    the learner's and evaluator's reports: a run called completed before it would have
    no final count in its record (a fault test once read it there and found none)."""
    states = {
        "L": {"state": "completed"},
        "E": {"state": "completed", "points": 5},
        "C": {"state": "running", "counted": 40},
    }
    v = run_verdict(states, ASSIGN, 5)
    assert (v.state, v.missing, v.counter_pending) == ("finishing", 0, True)
    states["C"] = {"state": "completed", "counted_transitions": 100}
    assert run_verdict(states, ASSIGN, 5).state == "completed"


def test_run_verdict_failure_first_and_with_a_reason():
    states = {
        "A0": {"state": "failed"},  # followed the learner, no reason of its own
        "L": {"state": "failed", "reason": "actor A0 died"},
        "E": {"state": "stopped", "reason": "learner failed"},
    }
    v = run_verdict(states, ASSIGN, 0)
    assert (v.state, v.service, v.reason) == ("failed", "L", "L: actor A0 died")


def test_run_verdict_stopped_names_the_service():
    states = {"L": {"state": "completed"}, "E": {"state": "stopped", "reason": "by user"}}
    v = run_verdict(states, ASSIGN, 0)
    assert (v.state, v.reason) == ("stopped", "E: by user")


def test_a_batch_lost_in_a_router_restart_makes_a_gap_not_a_lost_count():
    """What a restarted router does (tests/test_topology.py, where `gaps == 0` once
    failed): batch k dies with the router while batch k+1, sent after it is back,
    arrives. The counter refuses k+1 (it expects k): one gap, nothing counted. No ack
    moves, so the actor resends both after `resend_after_s`; the counter then takes k
    and k+1. Every row is counted once: a gap is a refused batch that a resend answers,
    which is what the cluster checks with faults (`check_exact(..., faults=True)`:
    gaps <= resends, counted == published)."""
    n = 20
    sender = Sender(confirm=("counter",), credit_from="counter", resend_after_s=1.0)
    sender.on_ack("counter", 0, now=0.0, window=2 * n)
    counter = ReceiveCursor()
    counted: list[int] = []

    def deliver(seq: int) -> None:
        d = counter.take("a", seq, n)
        if d.took:
            counted.extend(range(seq + d.skip, seq + n))
            sender.on_ack("counter", counter.expected("a"), now=now)

    now = 0.0
    k0 = sender.send(n, b"k", now)  # lost: the router died with it
    now = 0.5
    k1 = sender.send(n, b"k+1", now)
    deliver(k1)  # arrives first
    assert counter.gaps == 1 and counted == []
    now = 1.6
    resent = sender.due(now)
    assert resent == [b"k", b"k+1"] and sender.resends == 2
    for seq in (k0, k1):
        deliver(seq)
    assert counted == list(range(2 * n)) and counter.gaps == 1
    assert counter.gaps <= sender.resends and sender.settled


def test_a_rejoining_actor_goes_on_from_the_least_of_the_learners_and_the_counters():
    from shared.net.protocol import Rejoin

    r = Rejoin("learner", "counter", since=100.0)
    r.ack("a", "learner", 41)
    assert r.positions(["a"], now=100.5) is None  # the counter's is waited for
    r.ack("a", "counter", 40)  # it lacks the step the dead actor had in flight
    assert r.positions(["a"], now=100.5) == {"a": 40}
    r.ack("a", "other", 7)  # another service's ack says nothing
    r.ack("a", "counter", "x")  # nor a malformed one
    assert r.positions(["a"], now=100.5) == {"a": 40}
    assert r.positions(["a", "b"], now=100.5) is None  # a group: every run first
    r.ack("b", "learner", 40)
    assert r.positions(["a", "b"], now=102.0) is None
    assert r.positions(["a", "b"], now=103.5) == {"a": 40, "b": 40}  # waited long enough
    alone = Rejoin("learner", None, since=0.0)  # a run that counts nothing
    alone.ack("a", "learner", 60)
    assert alone.positions(["a"], now=0.0) == {"a": 60}
