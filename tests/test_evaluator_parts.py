"""The evaluator service's parts in process, no bus: a resent point's fate, a group's
point taken together or not, the rows kept for history queries, a point's row.
(The order of points is tests/test_evaluator_order.py's.)"""

from __future__ import annotations

import collections

from services.evaluator.history import RowHistory
from services.evaluator.points import (
    GROUP_WAIT_S,
    ORDER_WAIT_S,
    REPUBLISH_AFTER_S,
    EvaluatorRun,
    GroupEval,
    eval_row,
    take_next,
)
from services.evaluator.policies import LearnerPolicy
from shared.config import make_config
from shared.net.messages import Weights
from shared.run.rollout import EvalResult


def weights(point: int, unreported: list[int] | None = None, run: str = "r", **stats) -> Weights:
    return Weights(run, version=point + 1, updates=10 * point, env_steps=100 * point,
                   episodes=point, eval_point=point, collisions_cum=3, actors=[], stats=stats,
                   incarnation="l", unreported=unreported or [])  # fmt: skip


def run(name: str = "r") -> EvaluatorRun:
    return EvaluatorRun(name, envs=[], policy=None, layout=[])  # type: ignore[arg-type]


def test_a_point_is_kept_once_and_a_resend_of_an_evaluated_one_republishes_its_row_late():
    st = run()
    assert not st.receive(weights(20), now=0.0)
    assert not st.receive(weights(20), now=1.0)  # pending already: evaluated once
    assert [m.eval_point for m in st.pending] == [20]
    st.pending.clear()
    st.row_out(20, now=10.0)
    assert st.points == 1
    assert not st.receive(weights(20), now=10.0 + REPUBLISH_AFTER_S)  # crossed the row
    assert st.receive(weights(20), now=10.0 + REPUBLISH_AFTER_S + 0.1)  # the row was lost
    assert not st.pending  # not evaluated again


def test_a_point_taken_without_an_earlier_one_names_the_ones_given_up():
    st = run()
    st.receive(weights(60, [20, 40]), now=0.0)
    st.published[20] = 0.0
    assert take_next(st, now=0.0) == (None, [])
    msg, given_up = take_next(st, now=ORDER_WAIT_S)
    assert msg is not None and msg.eval_point == 60 and given_up == [40]
    assert st.held_since is None and not st.pending


def group_of(n: int) -> tuple[GroupEval, list[EvaluatorRun]]:
    names = [f"r{i}" for i in range(n)]
    return GroupEval(names, venv=None, policy=None), [run(name) for name in names]  # type: ignore[arg-type]


def test_a_groups_point_is_taken_together_only_when_every_run_has_it():
    g, sts = group_of(3)
    for st in sts[:2]:
        st.receive(weights(20, run=st.run), now=0.0)
    assert g.take_together(sts) == []  # run 2 lacks it: nothing taken
    assert all(len(st.pending) == 1 for st in sts[:2])
    assert g.take_together(sts[:2]) == []  # run 2 not started yet
    sts[2].receive(weights(40, run="r2"), now=0.0)
    assert g.take_together(sts) == []  # run 2's earliest is a later point
    sts[2].receive(weights(20, run="r2"), now=0.0)
    ready = g.take_together(sts)
    assert [(st.run, msg.eval_point) for st, msg in ready] == [("r0", 20), ("r1", 20), ("r2", 20)]
    assert [len(st.pending) for st in sts] == [0, 0, 1]


def test_a_groups_point_waiting_for_an_earlier_one_is_not_taken_together():
    g, sts = group_of(2)
    for st in sts:
        st.receive(weights(40, [20], run=st.run), now=0.0)
    sts[0].published[20] = 0.0
    assert g.take_together(sts) == []  # run 1 has neither evaluated 20 nor got it
    sts[1].published[20] = 0.0
    assert len(g.take_together(sts)) == 2


def test_a_group_waits_group_wait_s_from_the_first_look_then_goes_alone():
    g, _ = group_of(2)
    assert not g.waited_out(100.0)
    assert not g.waited_out(100.0 + GROUP_WAIT_S / 2)
    assert g.waited_out(100.0 + GROUP_WAIT_S)


def test_history_keeps_the_newest_runs_rows_and_a_restarted_run_starts_afresh():
    h = RowHistory(keep=2)
    h.start("a")
    h.remember("a", "running", {"episode": 20})
    h.start("b")
    h.start("c")  # a is the oldest: dropped
    assert h.get("a") is None and h.get("b") == ("running", [])
    h.remember("c", "running", {"episode": 20, "x": 1})
    h.remember("c", "completed")
    state, rows = h.get("c")
    rows.append({"episode": 99})  # a copy: the kept rows stay
    assert state == "completed" and h.get("c") == ("completed", [{"episode": 20, "x": 1}])
    assert h.row("c", 20) == {"episode": 20, "x": 1} and h.row("c", 40) is None
    h.start("c")
    assert h.get("c") == ("running", [])


def test_history_answers_name_the_attempt_their_rows_are_of_and_a_reader_takes_its_own():
    """A retried run's history get is answered by the new attempt's evaluator and, maybe
    first, by the ended attempt's: the reader takes the rows of its own attempt."""
    from shared.net.control import history_rows
    from shared.net.messages import History
    from shared.net.wire import encode

    h = RowHistory(keep=1)
    h.start("r", 1)
    assert h.answer("r") == ("running", [], 1)
    h.start("s", 2)  # "r" dropped: its attempt with it
    assert h.answer("r") is None and h.answer("s") == ("running", [], 2)
    h.remember("s", "running", {"episode": 4})  # a row keeps the attempt
    assert h.answer("s") == ("running", [{"episode": 4}], 2)

    class Replies:  # the bus's get: each evaluator's reply, the ended attempt's first
        def get(self, key: str, timeout: float) -> list[bytes]:
            return [
                encode(History("r", source="eval", rows=[{"episode": 8}], state="x", attempt=1)),
                encode(History("r", source="eval", rows=[{"episode": 4}], state="x", attempt=2)),
            ]

    assert history_rows(Replies(), "r", attempt=2) == [{"episode": 4}]  # type: ignore[arg-type]
    assert history_rows(Replies(), "r", attempt=3) == []  # type: ignore[arg-type]
    assert history_rows(Replies(), "r") == [{"episode": 8}]  # type: ignore[arg-type]


def test_a_row_carries_the_points_numbers_and_the_learners_and_counters_stats():
    msg = weights(40, counter={"count1_pct": 12.5, "table_size": 7}, bonus={"bonus_mean": 0.3},
                  steps_per_sec=50.0, replay_ratio=1.0)  # fmt: skip
    row = eval_row(msg, EvalResult(success_rate=0.5, eval_return=-3.0, episodes=2, steps=50))
    assert (row["episode"], row["env_steps"], row["updates"], row["policy_version"]) == (
        40, 4000, 400, 41,
    )  # fmt: skip
    assert (row["count1_pct"], row["table_size"], row["counted_transitions"]) == (12.5, 7, 0)
    assert (row["bonus_mean"], row["bonus_std"]) == (0.3, 0.0)
    assert row["steps_per_sec"] == row["train_steps_per_sec"] == 50.0
    assert (row["success_rate"], row["eval_return"], row["collisions_cum"]) == (0.5, -3.0, 3)


def test_a_lockstep_run_is_evaluated_with_the_learners_own_act_on_its_own_worlds():
    cfg = make_config({"task": "speaker_listener", "eval_episodes": 12, "hidden": [16, 16]})
    st = EvaluatorRun.open("r", cfg)
    assert len(st.envs) == 10 and not isinstance(st.policy, LearnerPolicy)
    lockstep = EvaluatorRun.open("r", cfg.model_copy(update={"interleave": "lockstep"}))
    assert isinstance(lockstep.policy, LearnerPolicy)
    assert isinstance(st.pending, collections.deque)
