"""The run monitor in process: the one rule by which the API, `macb start` (RunWatch)
and the services end a run, fed events with the caller's clock."""

from __future__ import annotations

from shared.net.messages import Assignment
from shared.net.monitor import Graces, PeerGrace, RunMonitor

ASSIGN = Assignment.from_wire(
    {"learner": "L", "counter": "C", "evaluator": "E", "actors": ["A0", "A1"]}
)
GRACES = Graces(peer_s=30.0, counter_s=120.0, completion_s=5.0, start_s=60.0)


def monitor(**kw) -> RunMonitor:
    return RunMonitor(ASSIGN, started=0.0, graces=GRACES, **kw)


def running(m: RunMonitor, now: float = 1.0) -> RunMonitor:
    for svc in ("L", "C", "E", "A0", "A1"):
        m.status(svc, "running", {}, now)
    return m


def test_reports_decide_first_a_failure_with_its_reason_then_a_stop():
    m = running(monitor())
    m.status("A0", "failed", {}, 2.0)  # a follower, no reason
    m.status("L", "failed", {"reason": "out of memory"}, 2.0)
    assert m.decide(3.0).state == "failed" and m.decide(3.0).reason == "L: out of memory"
    s = running(monitor())
    s.status("E", "stopped", {"reason": "asked"}, 2.0)
    assert (s.decide(3.0).state, s.decide(3.0).reason) == ("stopped", "E: asked")


def test_a_run_completes_when_every_report_and_point_is_in():
    m = running(monitor())
    m.status("L", "completed", {}, 10.0)
    m.status("E", "completed", {"points": 3}, 10.0)
    m.points_seen(2)
    m.status("C", "completed", {}, 10.0)
    first = m.decide(10.5)
    assert first.state == "running" and first.ask_history  # a point is missing: ask once
    assert m.decide(10.6).state == "running" and not m.decide(10.6).ask_history
    m.points_seen()
    assert m.decide(10.7).state == "completed" and m.decide(10.7).reason is None


def test_what_never_comes_is_given_up_after_the_completion_grace_and_named():
    m = running(monitor())
    m.status("L", "completed", {}, 10.0)
    m.status("E", "completed", {"points": 4}, 10.0)
    m.points_seen(3)
    assert m.decide(11.0).ask_history
    assert m.decide(15.0).state == "running"  # within the grace (5 s after the evaluator)
    late = m.decide(15.1)
    assert late.state == "completed"
    assert "1 of 4 metric points" in late.reason and "counter's final report" in late.reason


def test_a_lost_service_is_waited_for_then_given_up_naming_it():
    m = running(monitor())
    m.peer("actor", "A1", False, 100.0)
    assert m.waiting() == "actor A1 is down; waiting up to 30 s for it"
    assert m.decide(129.0).state == "running"
    m.peer("actor", "A1", True, 129.0)  # back within the grace
    assert m.waiting() is None and m.decide(200.0).state == "running"
    m.peer("learner", "L", False, 200.0)
    gone = m.decide(230.0)
    assert gone.state == "failed" and gone.reason.startswith("learner L died")
    assert "within 30 s" in gone.reason


def test_services_of_other_runs_and_finished_ones_do_not_count():
    m = running(monitor())
    m.peer("learner", "other-learner", False, 0.0)
    m.status("A0", "completed", {}, 1.0)
    m.peer("actor", "A0", False, 1.0)  # its part is done
    assert m.waiting() is None and m.decide(500.0).state == "running"


def test_the_counter_has_a_grace_of_its_own():
    m = running(monitor())
    m.peer("counter", "C", False, 10.0)
    assert m.waiting() == "counter C is down; waiting for it to return"
    assert m.decide(10.0 + 119).state == "running"  # longer than a peer's 30 s
    m.peer("counter", "C", True, 130.0)
    assert m.waiting() is None
    m.peer("counter", "C", False, 200.0)
    d = m.decide(321.0)
    assert (d.state, d.reason) == ("failed", "counter C did not come back")


def test_a_run_no_service_takes_fails_after_the_start_timeout():
    m = monitor()
    assert m.decide(59.0).state == "running"
    d = m.decide(60.5)
    assert d.state == "failed" and d.reason == "no service took the run within 60 s"
    assert running(monitor()).decide(1000.0).state == "running"


def test_a_watcher_started_after_the_evaluator_ended_counts_its_grace_from_then():
    states = {"L": {"state": "completed"}, "E": {"state": "completed", "points": 2}}
    m = RunMonitor(ASSIGN, started=50.0, graces=GRACES, states=states, points=2)
    assert m.decide(54.0).state == "running"  # the counter's report may still come
    assert m.decide(55.5).state == "completed"


def test_peer_grace_keeps_the_first_loss_and_forgets_what_it_gave_up():
    g = PeerGrace(10.0)
    assert g.lost("actor", "A0", 0.0) and not g.lost("actor", "A0", 5.0)
    assert "A0" in g and g.expired(9.9) == []
    assert g.expired(10.0) == [("actor", "A0")] and not g
    assert not g.back("A0")
