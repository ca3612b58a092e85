"""The run monitor in process: the one rule by which the API, `macb start` (RunWatch)
and the services end a run, fed events with the caller's clock, including the end of
a run no service serves any more, and the one reader of a liveliness key."""

from __future__ import annotations

from shared.net import bus as keys
from shared.net.control import RunWatch
from shared.net.messages import Assignment, Metrics
from shared.net.monitor import (
    LIVE_PREFIX,
    Decision,
    Graces,
    PeerGrace,
    RunMonitor,
    live_peer,
    serving,
)
from shared.net.wire import encode

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


def test_a_run_its_early_stop_rule_ended_completes_with_the_learners_reason():
    """The learner completes a run where its `early_stop` rule held, saying why: the
    run is completed (not stopped, not failed) and its reason is the learner's, which
    the API stores as the run's and the dashboard shows; a late point adds its note."""
    why = "early_stop success_at_least at episode 6: success rate >= 0.9 at 2 point(s) in a row"
    m = running(monitor())
    m.status("L", "completed", {"reason": why, "stopped_at": 6}, 10.0)
    m.status("E", "completed", {"points": 2}, 10.0)
    m.status("C", "completed", {}, 10.0)
    m.points_seen(2)
    assert m.decide(10.5) == Decision("completed", why)
    late = running(monitor())
    late.status("L", "completed", {"reason": why}, 10.0)
    late.status("E", "completed", {"points": 3}, 10.0)
    late.status("C", "completed", {}, 10.0)
    late.points_seen(2)
    late.decide(11.0)  # (asks the history once)
    end = late.decide(15.1)
    assert end.state == "completed" and end.reason.startswith(why + "; 1 of 3 metric points")


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


def test_a_status_from_a_service_the_run_was_not_assigned_is_not_its():
    """A run queued again may start on learner L while L2, the learner of its ended
    attempt, still answers that attempt's stop on the same run's key: L2's "stopped"
    must not stop the new attempt, nor show among its services."""
    m = running(monitor())
    m.status("L2", "stopped", {"reason": "stopped by user"}, 2.0)
    m.status("A9", "failed", {"reason": "an old actor"}, 2.0)
    assert m.decide(3.0).state == "running"
    assert set(m.states) == {"L", "C", "E", "A0", "A1"}
    m.status("L", "stopped", {"reason": "asked"}, 4.0)  # its own learner still counts
    assert (m.decide(5.0).state, m.decide(5.0).reason) == ("stopped", "L: asked")


def test_a_service_whose_loss_came_before_its_completed_status_is_not_waited_for():
    """A service that completes and exits: its token's loss may be seen before its
    status (they come on subscriptions of their own), which then ends the wait."""
    m = running(monitor())
    m.peer("actor", "A0", False, 1.0)
    m.peer("counter", "C", False, 1.0)
    assert m.waiting() is not None
    m.status("A0", "completed", {}, 1.1)
    m.status("C", "completed", {}, 1.1)
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


# ---------------------------------------------------------------- one liveliness key reader
def test_a_liveliness_key_is_read_in_one_place_as_the_bus_writes_it():
    assert keys.k_live("actor", "a0").startswith(LIVE_PREFIX)
    assert live_peer(keys.k_live("actor", "a0")) == ("actor", "a0")
    for other in ("macb/live/actor", "macb/live/actor/a/b", "macb/run/r/live/x", "bad", ""):
        assert live_peer(other) is None, other


# ---------------------------------------------------------------- a run no service serves
def serves(run: str | None) -> dict[str, dict]:
    return {"L": {"id": "L", "role": "learner", "run": run}, "C": {"runs": [run]}}


def test_a_run_no_service_serves_ends_by_its_last_point_after_the_wait():
    m = running(monitor(episodes=12))
    m.points_seen(3, last_episode=12)
    alive = {("learner", "L")}
    assert m.unserved("r", {}, alive, now=10.0, settle_s=15.0, wait_s=30.0) is None  # young
    assert m.unserved("r", {}, alive, 20.0, 15.0, 30.0) is None and m.unserved_since == 20.0
    assert m.unserved("r", serves("r"), alive, 40.0, 15.0, 30.0) is None  # served again
    assert m.unserved_since is None
    assert m.unserved("r", {}, alive, 41.0, 15.0, 30.0) is None
    assert m.unserved("r", {}, alive, 70.0, 15.0, 30.0) is None
    end = m.unserved("r", {}, alive, 71.0, 15.0, 30.0)
    assert end == Decision("completed", "its end was not observed (the API was not listening)")
    assert not end.stop


def test_a_run_ended_unseen_before_its_last_point_failed_and_its_services_are_stopped():
    m = monitor(episodes=12, last_episode=8, watcher="macb start")
    end = m.unobserved_end()
    assert end.state == "failed" and end.stop
    assert "episode 8" in end.reason and "macb start was not listening" in end.reason
    assert monitor(episodes=0).unobserved_end().state == "failed"  # no length: no claim


def test_the_counter_alone_does_not_serve_a_run_and_a_learner_gone_unseen_gets_the_grace():
    assert serving("r", ASSIGN.services(), serves(None)) == []
    assert serving("r", ASSIGN.services(), {"A1": {"runs": ["r"]}}) == ["A1"]
    m = running(monitor())
    m.unserved("r", serves("r"), set(), 20.0, 15.0, 30.0)  # its info answers: not lost
    assert m.waiting() is None
    m.unserved("r", {}, set(), 20.0, 15.0, 30.0)  # neither token nor info
    assert m.waiting() == "learner L is down; waiting up to 30 s for it"
    assert m.decide(51.0).state == "failed"


def test_graces_say_when_a_run_has_settled_and_how_long_unserved_is_waited():
    assert GRACES.settle_s == 15.0
    assert GRACES.unserved_s(3.0) == 30.0 and GRACES.unserved_s(45.0) == 45.0
    assert [Decision(s).stop for s in ("running", "completed", "stopped", "failed")] == [
        False,
        False,
        True,
        True,
    ]


# ---------------------------------------------------------------- the CLI's adapter
class QuietBus:
    """A bus on which nothing serves the run: no info answers, no token."""

    def __init__(self) -> None:
        self.asked = 0

    def get(self, key: str, timeout: float = 1.0) -> list[bytes]:
        self.asked += 1
        return []

    def subscribe(self, key: str, callback) -> None:
        pass

    def watch_liveliness(self, key: str, callback) -> None:
        pass


def test_macb_starts_watch_ends_a_run_no_service_serves_by_the_same_rule():
    graces = Graces(peer_s=0.0, counter_s=120.0, completion_s=5.0, start_s=60.0)
    w = RunWatch("r", ASSIGN, episodes=4, check_s=0.0, graces=graces)
    w.monitor.started -= 20.0  # settled (a quarter of the start grace)
    bus = QuietBus()
    w.attach(bus)  # type: ignore[arg-type]
    w._on_live(keys.k_live("learner", "L"), True)  # its token is up: not lost, just idle
    w._on_metrics(keys.k_metrics("r", "eval"), encode(Metrics("r", "eval", {"episode": 4})))
    assert w.state() == "running" and bus.asked == 1  # the unserved clock starts
    assert w.decision() == Decision(
        "completed", "its end was not observed (macb start was not listening)"
    )
    assert w.state() == "completed" and bus.asked == 2  # once over, it stays so


def test_macb_starts_watch_asks_who_serves_no_more_than_every_check():
    w = RunWatch("r", ASSIGN, episodes=4, check_s=3600.0)
    bus = QuietBus()
    w.attach(bus)  # type: ignore[arg-type]
    assert w.state() == "running" and w.state() == "running" and bus.asked == 0
