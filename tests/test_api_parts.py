"""The API's parts in process, no bus and no server: the queue pass (what starts on which
services, in which groups), a run's watch, the reconciliation of the store with what the
bus shows, the run book's store writes, and the metric points table."""

from __future__ import annotations

import dataclasses
from typing import Any

import pytest

from services.api.planner import Invalid, QueuePass, Start
from services.api.points import Points
from services.api.reconcile import reconcile_run, stale_runs, worker_rows
from services.api.runbook import RunBook
from services.api.store import Store
from services.api.watch import Ending, Watch, flat_row
from shared.net import bus as keys
from shared.net.messages import Assignment, Metrics, Resumed, Status
from shared.net.monitor import Graces, serving, start_lost
from shared.net.wire import encode
from tests.harness import TINY

GRACES = Graces(peer_s=30.0, counter_s=120.0, completion_s=5.0, start_s=60.0)
ASSIGN = {"counter": "C", "learner": "L1", "evaluator": "E1", "actors": ["A1"]}
LOCKSTEP = {**TINY, "interleave": "lockstep"}


def infos(learners: int = 2, evaluators: int = 2, actors: int = 2) -> list[dict[str, Any]]:
    """Free services as `discover` gives them, and one counter."""
    out = [{"id": "C", "role": "counter", "run": None}]
    out += [{"id": f"L{i}", "role": "learner", "run": None} for i in range(1, learners + 1)]
    out += [{"id": f"E{i}", "role": "evaluator", "run": None} for i in range(1, evaluators + 1)]
    return out + [{"id": f"A{i}", "role": "actor", "run": None} for i in range(1, actors + 1)]


def queued(run_id: str, exp: str = "x", actors: int = 1, reason=None, **config) -> dict:
    """A queued run as the store's row gives it."""
    cfg = {**LOCKSTEP, "seed": len(run_id), **config}
    return {"id": run_id, "experiment_id": exp, "actors": actors, "reason": reason, "config": cfg}


# ---------------------------------------------------------------- the queue pass
def test_the_queue_starts_runs_oldest_first_on_free_services_and_the_rest_wait():
    plan = QueuePass([queued("r1"), queued("r2"), queued("r3")], infos(), reserved=set())
    started = []
    for start in plan.proposals():
        assert isinstance(start, Start) and start.assign.group is None
        started.append((start.ids, start.assign.to_wire()))
        plan.took(start)
    assert started == [
        (["r1"], {"counter": "C", "learner": "L1", "evaluator": "E1", "actors": ["A1"]}),
        (["r2"], {"counter": "C", "learner": "L2", "evaluator": "E2", "actors": ["A2"]}),
    ]
    assert plan.waiting == {"r3": "waiting: no free learner, evaluator, 1 actor(s)"}


def test_a_start_not_claimed_leaves_its_services_to_the_next_run():
    plan = QueuePass([queued("r1"), queued("r2")], infos(), reserved=set())
    first, second = list(plan.proposals())  # r1's claim failed: took() never called
    assert first.assign == second.assign and second.ids == ["r2"]


def test_services_reserved_by_running_runs_are_busy_and_the_callers_infos_untouched():
    given = infos(learners=2, evaluators=1, actors=2)
    plan = QueuePass([queued("r1")], given, reserved={"E1", "L1", "A1"})
    assert list(plan.proposals()) == []
    assert plan.waiting == {"r1": "waiting: no free evaluator"}
    assert all(i["run"] is None for i in given)


def test_a_waiting_reason_is_written_only_where_it_changes():
    why = "waiting: no free learner"
    plan = QueuePass(
        [queued("r1", reason=why), queued("r2"), queued("r3", actors=2)],
        infos(learners=0),
        reserved=set(),
    )
    assert list(plan.proposals()) == []
    assert plan.waiting == {"r2": why, "r3": why}


def test_a_stored_config_this_api_refuses_is_proposed_as_invalid():
    plan = QueuePass([queued("r1", episodes=-3), queued("r2")], infos(), reserved=set())
    bad, good = list(plan.proposals())
    assert isinstance(bad, Invalid) and bad.run == "r1" and bad.reason.startswith("invalid config")
    assert isinstance(good, Start) and good.ids == ["r2"] and good.assign.learner == "L1"


def test_runs_that_can_share_a_group_start_together_up_to_the_group_size():
    runs = [queued("a1"), queued("b1", exp="y"), queued("a22"), queued("a333"), queued("a4444")]
    plan = QueuePass(runs, infos(), reserved=set(), group_size=3)
    first = next(iter(plan.proposals()))
    assert first.ids == ["a1", "a22", "a333"] and list(first.assign.group or ()) == first.ids
    assert [cfg.seed for _, cfg in first.members] == [2, 3, 4]
    plan.took(first)
    rest = list(plan.proposals())
    assert [s.ids for s in rest] == [["b1"], ["a4444"]]  # another experiment; then the rest
    async_lead = QueuePass([queued("s1", interleave="async"), queued("s2")], infos(), set(), 3)
    assert [s.ids for s in async_lead.proposals()] == [["s1"], ["s2"]]


def test_runs_with_an_early_stop_rule_share_a_group_with_runs_without():
    """The cluster ends a group's run by its rule and goes on with the others, so the
    planner groups such runs as any others (per-run field: a rule on some runs only)."""
    rule = {"rule": "no_improvement", "patience": 2}
    runs = [queued("e1", early_stop=rule), queued("e22"), queued("e333", early_stop=rule)]
    plan = QueuePass(runs, infos(), reserved=set(), group_size=3)
    first = next(iter(plan.proposals()))
    assert first.ids == ["e1", "e22", "e333"] and list(first.assign.group or ()) == first.ids


def test_a_started_runs_rows_are_a_new_attempt_and_the_queued_rows_stay():
    row = {**queued("r1"), "services": {"L0": {"state": "failed"}}, "live": {"eval": {}}}
    plan = QueuePass([row], infos(), reserved=set())
    start = next(iter(plan.proposals()))
    (attempt,) = start.attempt_rows()
    assert (
        attempt["assign"] == start.assign.to_wire() and attempt["services"] == attempt["live"] == {}
    )
    assert row["services"] == {"L0": {"state": "failed"}} and "assign" not in row


# ---------------------------------------------------------------- one run's watch
def watch(episodes: int = 12, started: float = 0.0, last: int = 0, run: str = "r1") -> Watch:
    row = {"id": run, "assign": ASSIGN, "config": {"episodes": episodes}}
    return Watch.of(row, started, GRACES, (0, 0, last))


def test_flat_row_keeps_only_what_json_can_say():
    data = {"a": 1.5, "b": float("nan"), 3: "x", "c": [1, float("inf"), "s", None], "d": {"e": {}}}
    data["f"] = object()
    assert flat_row(data) == {"a": 1.5, "b": None, "c": [1, "s"], "d": {"e": {}}}


def test_an_evaluation_row_is_a_point_and_every_source_its_latest_stats():
    w = watch()
    row = w.metrics(Metrics("r1", source="eval", data={"episode": 4, "success_rate": 0.5}))
    assert row == {"episode": 4, "success_rate": 0.5} and w.live == {"eval": row}
    assert w.metrics(Metrics("r1", source="eval", data={"episode": "4"})) is None
    assert w.metrics(Metrics("r1", source="learner", data={"updates": 7})) is None
    assert w.live == {"eval": row, "learner": {"updates": 7}} and w.live_dirty
    assert not w.live_due(0.5) and w.live_due(1.5)  # saved at most every second
    w.live_saved(1.5)
    assert not w.live_due(10.0)


def test_a_resumed_learner_leaves_one_note_per_resume():
    w = watch()
    cut = Resumed("r1", from_episode=8, updates=3, replay_rows=9, held_batches=0, seconds=0.1)
    resumed = Status("r1", service="L1", state="running", detail={}, resumed=cut)
    note = "learner L1 restarted and resumed from the cut at episode 8"
    assert w.status(resumed, 1.0) == note
    assert w.status(resumed, 2.0) is None and w.notes == [note]  # said again in every status
    log = dataclasses.replace(cut, from_episode=None)
    no_cut = Status("r1", service="L1", state="running", detail={}, resumed=log)
    assert w.status(no_cut, 3.0).endswith("from its log (no cut yet)")
    actor = Status("r1", service="A1", state="running", detail={}, resumed=cut)
    assert w.status(actor, 4.0) is None and w.states["A1"]["state"] == "running"
    assert w.reason() == "; ".join(w.notes)


def test_a_run_ended_unseen_is_completed_only_with_its_last_point_stored():
    assert watch(episodes=12, last=12).unobserved_end() == Ending(
        "completed", "its end was not observed (the API was not listening)", False
    )
    failed = watch(episodes=12, last=8).unobserved_end()
    assert failed.status == "failed" and failed.stop and "episode 8" in failed.reason


# ---------------------------------------------------------------- the store vs the bus
def serving_infos(run: str | None) -> dict[str, dict[str, Any]]:
    return {
        "C": {"id": "C", "role": "counter", "run": None, "runs": ["r1"]},
        "L1": {"id": "L1", "role": "learner", "run": run},
        "E1": {"id": "E1", "role": "evaluator", "run": run},
    }


def test_serving_counts_the_runs_services_by_their_info_but_not_the_counter():
    services = watch().services()
    assert serving("r1", services, serving_infos("r1")) == ["L1", "E1"]
    assert serving("r1", services, serving_infos(None)) == []
    assert serving("r1", services, {"A1": {"role": "actor", "runs": ["r1"]}}) == ["A1"]


def test_a_run_no_service_serves_ends_after_the_wait_by_its_stored_points():
    w = watch(episodes=12, started=0.0, last=12)
    alive = {("learner", "L1")}
    args = dict(alive=alive, settle_s=15.0, wait_s=30.0)
    assert reconcile_run(w, {}, now=10.0, **args) is None  # too young to judge
    assert reconcile_run(w, {}, now=20.0, **args) is None and w.unserved_since == 20.0
    assert reconcile_run(w, serving_infos("r1"), now=40.0, **args) is None  # served again
    assert w.unserved_since is None
    assert reconcile_run(w, {}, now=41.0, **args) is None
    assert reconcile_run(w, {}, now=70.0, **args) is None
    ending = reconcile_run(w, {}, now=71.0, **args)
    assert ending is not None and ending.status == "completed" and not ending.stop


def test_a_learner_gone_unseen_is_given_the_peer_grace():
    w = watch()
    reconcile_run(w, serving_infos("r1"), {("learner", "L1")}, 20.0, 15.0, 30.0)
    assert w.monitor.waiting() is None
    reconcile_run(w, {"E1": serving_infos("r1")["E1"]}, set(), 20.0, 15.0, 30.0)
    assert w.monitor.waiting() == "learner L1 is down; waiting up to 30 s for it"
    assert w.monitor.decide(51.0).state == "failed"


def test_a_service_that_missed_its_start_is_sent_it_again_on_the_second_look_and_not_often():
    """While some service of the run serves it, an assigned one that answers, has said
    nothing in this attempt and serves the run not at all (a counter, ready: or holds
    another attempt of it, restored from its disk) missed its start: it is to be sent
    again, on a second look in a row and at most every `every_s`. One that said
    something got it (an actor that completed and let the run go); one that does not
    answer is the peer graces'; a counter not ready, or one that names no attempt
    (older), is left; an arm that counts nothing learns without its counter."""
    w = watch()
    w.attempt = 2
    assert not w.counts, "an arm that counts nothing learns without its counter"
    counting = {"id": "r1", "assign": ASSIGN, "config": {"explore": "dis-macb"}}
    assert Watch.of(counting, 0.0, GRACES, (0, 0, 0)).counts

    def infos(held: dict | None = None, ready: bool = True, **runs: str | None) -> dict:
        """C holds `held` (None: nothing of r1); L1, E1, A1 serve r1 unless given."""
        out = {"C": {"id": "C", "role": "counter", "ready": ready, "runs": {}}}
        if held is not None:
            out["C"]["runs"] = {"r1": held}
        for sid, role in (("L1", "learner"), ("E1", "evaluator"), ("A1", "actor")):
            out[sid] = {"id": sid, "role": role, "run": runs.get(sid, "r1")}
        return out

    def lost(infos: dict, said: tuple = (), counts: bool = True) -> str | None:
        return start_lost(w.run, w.assign, w.attempt, infos, said, counts)

    assert lost(infos()) == "counter C does not hold the run"
    assert lost(infos({"attempt": 1})) == "counter C holds attempt 1 of the run, not 2"
    assert lost(infos({"attempt": 2}, L1=None)) == "learner L1 does not serve the run"
    assert lost(infos({"attempt": 2}, A1=None)) == "actor A1 does not serve the run"
    assert lost(infos({"attempt": 2}, E1="other")) == "evaluator E1 does not serve the run"
    for fine, said, counts in (
        (infos({"attempt": 2}), (), True),
        (infos({"counted_transitions": 5}), (), True),  # an older counter: no attempt said
        (infos(ready=False), (), True),  # still restoring its tables
        (infos(), ("C",), True),  # it said something in this attempt: it got the start
        (infos(), (), False),  # an arm that counts nothing
        (infos({"attempt": 2}, A1=None), ("A1",), True),  # completed, let the run go
        ({k: v for k, v in infos().items() if k != "C"}, (), True),  # no counter answers
        (infos(L1=None, E1=None, A1=None), (), True),  # nobody serves it: not under way
    ):
        assert lost(fine, said, counts) is None, (fine, said, counts)
    assert start_lost(w.run, w.assign, None, infos({"attempt": 1}), ()) is None, "a starter's"
    due = w.lost_start.due
    assert not due(True, 10.0, 15.0), "a first look only"
    assert not due(False, 13.0, 15.0), "found again: the look starts over"
    assert not due(True, 16.0, 15.0)
    assert due(True, 19.0, 15.0), "two looks in a row"
    assert not due(True, 22.0, 15.0) and not due(True, 33.0, 15.0)
    assert due(True, 34.0, 15.0), "again once every_s has passed"


def test_services_that_rejoined_an_ended_run_are_to_be_stopped():
    statuses = {"done": "completed", "live": "running", "watched": "failed"}
    found = {
        "L1": {"id": "L1", "role": "learner", "run": "done"},
        "L2": {"id": "L2", "role": "learner", "run": "live"},
        "L3": {"id": "L3", "role": "learner", "run": "watched"},
        "L4": {"id": "L4", "role": "learner", "run": "gone"},
        "C": {"id": "C", "role": "counter", "run": "done"},
        "E1": {"id": "E1", "role": "evaluator", "run": None},
    }
    stale = stale_runs(
        found, {"watched"}, lambda r: {"status": statuses[r]} if r in statuses else None
    )
    assert [(s.service, s.run, s.status) for s in stale] == [("L1", "done", "completed")]
    assert stale[0].reason == "the run had completed while this service was down"
    assert str(stale[0]) == "learner L1 serves run done, which has completed"


def test_workers_are_the_liveliness_tokens_with_what_each_info_says():
    tokens = [keys.k_live("learner", "L1"), keys.k_live("actor", "A1"), "macb/live/bad"]
    rows = worker_rows(tokens, [{"id": "L1", "role": "learner", "run": "r1", "restarts": 2}])
    assert [(r["role"], r["id"], r["run"], r["restarts"], r["answers"]) for r in rows] == [
        ("actor", "A1", None, 0, False),
        ("learner", "L1", "r1", 2, True),
    ]


# ---------------------------------------------------------------- the run book
class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def book(tmp_path):
    store = Store(tmp_path / "api.sqlite3")
    runs = [{"id": r, "seed": 0, "point": {}, "config": TINY, "actors": 1} for r in ("r1", "r2")]
    store.create_experiment("x", "x", {"config": TINY}, runs)
    assert store.claim("r1", Assignment.from_wire(ASSIGN))
    clock = Clock()
    b = RunBook(store, GRACES, clock=clock)
    b.watch(store.run("r1"), started=0.0)
    yield b, store, clock
    store.close()


def status(state: str, service: str = "L1", run: str = "r1", **detail) -> tuple:
    typed = {k: detail.pop(k) for k in ("reason", "points", "final_seq", "resumed") if k in detail}
    msg = Status(run, service=service, state=state, detail=detail, **typed)
    return ("status", keys.k_status(run, service), encode(msg))


def metrics(
    episode: int, run: str = "r1", source: str = "eval", attempt: int | None = None, sr=0.1
) -> tuple:
    msg = Metrics(
        run, source=source, data={"episode": episode, "success_rate": sr}, attempt=attempt
    )
    return ("metrics", keys.k_metrics(run, source), encode(msg))


def test_events_write_points_states_and_notes_into_the_store(book):
    b, store, _ = book
    cut = Resumed("r1", from_episode=4, updates=3, replay_rows=9, held_batches=0, seconds=0.1)
    resumed = status("running", resumed=cut)
    came_up = b.handle([metrics(4), metrics(8), metrics(4), resumed, ("live", "bad", True)])
    assert not came_up
    assert [p["episode"] for p in store.points("r1")] == [4, 8]
    w = b.watches["r1"]
    assert w.points == 2 and w.last_episode == 8
    row = store.run("r1")
    assert row["services"]["L1"]["state"] == "running"
    assert row["reason"] == "learner L1 restarted and resumed from the cut at episode 4"
    b.handle([metrics(12, run="r2"), status("failed", run="r2")])  # a run not watched
    assert store.points("r2") == [] and store.run("r2")["services"] == {}


def test_a_lost_service_is_the_runs_reason_until_it_is_back(book):
    b, store, clock = book
    clock.now = 5.0
    assert not b.handle([("live", keys.k_live("actor", "A1"), False)])
    assert store.run("r1")["reason"] == "actor A1 is down; waiting up to 30 s for it"
    assert b.handle([("live", keys.k_live("actor", "A1"), True)])  # up: the queue may move
    assert store.run("r1")["reason"] is None and ("actor", "A1") in b.alive
    assert b.reserved() == {"L1", "E1", "A1"}


def test_a_decision_asks_for_missing_points_once_and_the_end_is_recorded(book):
    b, store, _ = book
    b.handle([metrics(4)] + [status("completed", s) for s in ("L1", "C", "A1")])
    b.handle([status("completed", "E1", points=2)])
    asked = []

    def fill_gaps(w: Watch) -> int:
        asked.append(w.run)
        return b.store_points(w.run, [{"episode": 8}])

    ending = b.decide(b.watches["r1"], 1.0, fill_gaps)
    assert asked == ["r1"] and ending == Ending("completed", None, False)
    w = b.watches["r1"]
    w.metrics(Metrics("r1", source="learner", data={"updates": 3}))
    b.end(w, ending)
    row = store.run("r1")
    assert (row["status"], row["live"]["learner"]) == ("completed", {"updates": 3})
    assert store.stops_to_send() == [] and w.ended is not None and b.reserved() == set()


def test_a_failure_records_its_stop_as_due_and_a_retry_supersedes_the_ended_attempt(book):
    b, store, _ = book
    b.handle([status("failed", "A1", reason="boom")])
    w = b.watches["r1"]
    ending = b.decide(w, 1.0, lambda w: 0)
    assert ending is not None and ending.status == "failed" and ending.stop
    b.end(w, ending)
    assert store.stops_to_send() == [("r1", "A1: boom")]
    assert not b.superseded(w)
    store.retry_runs("x")
    assert b.superseded(w)
    b.handle([metrics(4), status("running")])  # what the ended attempt still sends
    assert store.points("r1") == [] and store.run("r1")["services"] == {}


def test_a_late_row_of_an_attempt_stopped_and_retried_over_http_is_not_stored(book):
    """A stop and a retry over HTTP, both before the scheduler's next pass: the watch of
    the ended attempt is not yet marked ended when its evaluator's late row comes. The
    row is not stored on the queued run, and the new attempt's own row for that episode
    is (the store keeps an episode's first)."""
    b, store, _ = book
    b.handle([metrics(4, attempt=1, sr=0.11)])
    assert store.finish("r1", "stopped", "stopped by user", stop_sent=None)
    assert [r["id"] for r in store.retry_runs("x", ["r1"])] == ["r1"]
    old = b.watches["r1"]
    assert old.ended is None and old.attempt == 1  # the scheduler has not looked yet
    b.handle([metrics(8, attempt=1, sr=0.22)])  # the ended attempt's evaluator, late
    assert store.points("r1") == [] and old.points == 1
    store.stop_sent("r1")  # the scheduler's next pass: the stop goes out first
    assert store.claim("r1", Assignment.from_wire(ASSIGN))  # the retry starts
    new = b.watch(store.run("r1"), started=1.0)
    assert new.attempt == 2
    b.handle([metrics(e, attempt=2, sr=e / 10) for e in (4, 8, 12)])
    assert [(p["episode"], p["success_rate"]) for p in store.points("r1")] == [
        (4, 0.4),
        (8, 0.8),
        (12, 1.2),
    ]
    assert new.points == 3 and new.last_episode == 12


def test_a_late_status_of_an_attempt_stopped_and_retried_over_http_is_not_written(book):
    """As the late row above, for statuses: the ended attempt's watch, not yet marked
    ended, hears its services answer the stop. Their states and notes are not written
    onto the queued run (nor its next attempt), whose reason stays the retry's."""
    b, store, clock = book
    b.handle([status("running")])
    assert store.run("r1")["services"]["L1"]["state"] == "running"
    assert store.finish("r1", "stopped", "stopped by user", stop_sent=None)
    store.retry_runs("x", ["r1"])
    old = b.watches["r1"]
    assert old.ended is None and old.attempt == 1 and not b.superseded(old)
    cut = Resumed("r1", from_episode=4, updates=3, replay_rows=9, held_batches=0, seconds=0.1)
    b.handle([status("stopped", "E1"), status("running", "L1", resumed=cut)])  # late, attempt 1
    assert old.notes, "the watch itself heard them"
    b.show_waiting(old, "waiting: something")  # a waiting reason cleared, on the old watch
    b.save_live(old, clock())
    row = store.run("r1")
    assert row["services"] == {} and row["live"] == {}
    assert row["reason"].startswith("retried (attempt 2; was stopped")


def test_a_run_whose_stop_is_still_due_is_not_claimed_until_the_stop_is_sent(book):
    """A stop and a retry over HTTP after the scheduler's stop pass read nothing due: the
    stop (which names no attempt) is still to go on the bus, so the queue pass may not
    claim the run yet, or that Stop would end the attempt it starts."""
    _, store, _ = book
    assert store.finish("r1", "stopped", "stopped by user", stop_sent=None)
    store.retry_runs("x", ["r1"])
    assert store.run("r1")["status"] == "queued"
    assert store.stops_to_send() == [("r1", "retried (attempt 2; was stopped: stopped by user)")]
    assert not store.claim("r1", Assignment.from_wire(ASSIGN))
    assert not store.claim_all(["r1", "r2"], Assignment.from_wire(ASSIGN)), "all or none"
    assert store.run("r2")["status"] == "queued"
    store.stop_sent("r1")
    assert store.claim("r1", Assignment.from_wire(ASSIGN))
    assert store.run("r1")["attempts"] == 2


def test_a_run_stopped_over_http_is_not_decided_again(book):
    b, store, _ = book
    store.finish("r1", "stopped", "stopped by user", stop_sent=False)
    w = b.watches["r1"]
    assert b.decide(w, 2.0, lambda w: 0) is None and w.ended == 2.0


def test_running_runs_are_followed_once_and_one_whose_stored_assignment_is_refused_fails(book):
    b, store, _ = book
    assert store.claim("r2", Assignment.from_wire({**ASSIGN, "learner": "L2"}))
    assert store.run("r2")["assign"] == {**ASSIGN, "learner": "L2"}  # the map, as REST shows it
    assert [r["id"] for r in b.to_follow(store.runs_with_status("running"))] == ["r2"]
    with store.db.tx() as c:  # as no API writes it: an assignment without actors
        c.execute("UPDATE runs SET assign = ? WHERE id = 'r2'", ('{"learner": "L2"}',))
    assert b.to_follow(store.runs_with_status("running")) == []  # r1 is followed already
    r2 = store.run("r2")
    assert r2["status"] == "failed" and "field 'actors' is missing" in r2["reason"]
    assert [run for run, _ in store.stops_to_send()] == ["r2"]  # its services told to stop


# ---------------------------------------------------------------- metric points
def test_points_are_numbered_in_arrival_order_and_an_episode_is_stored_once(tmp_path):
    store = Store(tmp_path / "api.sqlite3")
    store.create_experiment(
        "x", "x", {}, [{"id": "r", "seed": 0, "point": {}, "config": TINY, "actors": 1}]
    )
    points = Points(store.db)
    assert points.add("r", [{"episode": 8, "seq": 99}, {"episode": 4}]) == 2
    assert points.add("r", [{"episode": 4}, {"episode": 12}]) == 1
    assert [(p["seq"], p["episode"]) for p in points.rows("r")] == [(1, 8), (2, 4), (3, 12)]
    page = points.page_json("r", since=1, limit=1)
    assert page == ('[{"seq": 2, "episode": 4}]', 1, 2, 1, True), "attempt 1, one more after"
    assert points.page_json("r", since=2, limit=1)[4] is False, "the last one: none after"
    assert points.page_json("r", since=3) == ("[]", 0, 3, 1, False), "the cursor stays"
    assert points.page_json("none") == ("[]", 0, 0, 0, False), "no such run"
    assert points.stats(["r", "none"]) == {"r": (3, 3, 12), "none": (0, 0, 0)}
    assert points.add("r", [{"episode": 16}], attempt=2) == 0, "not the run's attempt"
    assert points.add("r", [{"episode": 16}], attempt=1) == 1
    assert points.add("none", [{"episode": 4}]) == 0, "no such run"
    store.close()


def test_a_users_stop_leaves_a_stop_to_send_for_a_run_started_since_it_was_read(tmp_path):
    """POST /runs/{id}/stop reads the run, then finishes it: a run the scheduler started
    in between (queued when read) still has services to stop. Whether a stop must go on
    the bus is read with the finish, in one statement (`stop_sent=None`)."""
    store = Store(tmp_path / "api.sqlite3")
    runs = [{"id": r, "seed": 0, "point": {}, "config": TINY, "actors": 1} for r in ("r1", "r2")]
    store.create_experiment("x", "x", {"config": TINY}, runs)
    assert store.run("r1")["status"] == "queued"  # what the route read
    assert store.claim("r1", Assignment.from_wire(ASSIGN))  # the scheduler, meanwhile
    assert store.finish("r1", "stopped", "stopped by user", stop_sent=None)
    assert store.finish("r2", "stopped", "stopped by user", stop_sent=None)  # still queued
    assert store.stops_to_send() == [("r1", "stopped by user")]
    assert not store.finish("r1", "stopped", "again", stop_sent=None)  # ended: no change
