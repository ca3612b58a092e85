"""A run alone and a group's runs start and end through the same evaluator code (a run
alone is a group of one): a group once outlived its runs (the evaluator kept its ended
group and evaluated the next run with it), a bug only the group path had. A point whose
weights cannot be evaluated is refused as it comes, not met in the evaluation loop."""

from __future__ import annotations

import dataclasses
import logging

import pytest

from services.evaluator.history import RowHistory
from services.evaluator.main import EvaluatorService
from services.evaluator.policies import LearnerPolicy
from services.runs import LearnerProcesses, ServedRuns
from shared.config import make_config
from shared.core.networks import weights_as_arrays
from shared.net import bus as keys
from shared.net.messages import Assignment, Weights
from shared.net.wire import encode


def bare_evaluator() -> tuple[EvaluatorService, list[tuple[str, str]]]:
    """Only what starting, evaluating and ending runs use: no bus."""
    ev = EvaluatorService.__new__(EvaluatorService)
    ev.runs, ev.group, ev.history, ev._retired = {}, None, RowHistory(), set()
    ev.took_points = LearnerProcesses()
    ev.active, ev.log = {}, logging.getLogger("test")
    ev.served = ServedRuns(8, None, ev.log)  # (the attempts served: none named here)
    statuses: list[tuple[str, str]] = []
    ev.listen = lambda *a, **k: None  # type: ignore[method-assign]
    ev.publish_status = lambda run, state, **d: statuses.append((run, state))  # type: ignore[method-assign]
    ev.publish_metrics = lambda *a, **k: None  # type: ignore[method-assign]
    ev.free = lambda run: ev.active.pop(run, None)  # type: ignore[method-assign]
    return ev, statuses


def start(ev: EvaluatorService, runs: list[str]) -> None:
    group = {"group": runs} if len(runs) > 1 else {}
    assign = Assignment.from_wire(
        {"learner": "l", "counter": "c", "actors": ["a0"], "evaluator": "e", **group}
    )
    for seed, run in enumerate(runs):
        cfg = make_config({"task": "speaker_listener", "interleave": "lockstep", "seed": seed,
                           "eval_episodes": 2, "episode_len": 5, "hidden": [8, 8]})  # fmt: skip
        ev.active[run] = cfg
        ev.on_start(run, cfg, assign)


def point(run: str, episode: int) -> Weights:
    return Weights(run, version=1, updates=0, env_steps=0, episodes=episode, eval_point=episode,
                   collisions_cum=0, actors=[], stats={}, incarnation="l")  # fmt: skip


@pytest.mark.parametrize("size", [1, 3])
@pytest.mark.parametrize("how", ["completed", "stopped"])
def test_the_runs_group_ends_with_its_last_run_alone_or_in_a_group(size: int, how: str):
    ev, statuses = bare_evaluator()
    runs = [f"r{i}" for i in range(size)]
    start(ev, runs)
    assert ev.group is not None and ev.group.runs == runs
    assert (ev.group.policy is not None) == (size > 1)  # a group's worlds as one
    for i, run in enumerate(runs):
        if how == "completed":
            ev.on_learner_completed(run)
        else:
            ev.on_stop(run, "asked")
        left = runs[i + 1 :]
        assert list(ev.runs) == left
        assert (ev.group is not None) == bool(left)  # kept while a run of it is served
    assert ev.group is None and not ev.tick()
    if how == "completed":
        assert statuses[-size:] == [(run, "completed") for run in runs]
    start(ev, ["next"])  # the next run is served as its own group, not the old one
    assert ev.group is not None and ev.group.runs == ["next"] and ev.group.policy is None


def test_a_run_alone_evaluates_its_next_point_at_once_and_in_order():
    ev, _ = bare_evaluator()
    start(ev, ["r"])
    st = ev.runs["r"]
    weights = point("r", 2)
    st.policy.load = lambda actors: None  # type: ignore[method-assign] (untrained actors)
    st.receive(point("r", 4), now=0.0)
    st.pending[0].unreported.append(2)  # 4 names 2, not here yet: it waits
    assert not ev.tick() and st.points == 0
    st.receive(weights, now=0.0)
    ev.tick()  # no group wait for a group of one: 2, then 4
    ev.tick()
    assert st.points == 2 and [p for p in st.published] == [2, 4]


def test_a_groups_point_only_some_runs_have_goes_alone_after_the_wait_one_at_a_time():
    from services.evaluator.points import GROUP_WAIT_S

    clock = [100.0]
    ev, _ = bare_evaluator()
    ev.clock = lambda: clock[0]  # type: ignore[method-assign]
    start(ev, ["r0", "r1"])
    for st in ev.runs.values():
        st.policy.load = lambda actors: None  # type: ignore[method-assign]
    ev.runs["r0"].receive(point("r0", 2), now=clock[0])
    ev.runs["r1"].receive(point("r1", 4), now=clock[0])  # (its 2 is on its way)
    assert not ev.tick()  # not every run has 2: it waits
    clock[0] += GROUP_WAIT_S
    assert ev.tick()  # r0's 2 alone; r1's 4 is still there
    assert (ev.runs["r0"].points, ev.runs["r1"].points, len(ev.runs["r1"].pending)) == (1, 0, 1)


# ------------------------------------------------------------ a point's weights refused
@pytest.mark.parametrize(
    "spoil, why",
    [
        (lambda w: {"actors": w.actors[:1]}, "weights: weights for 1 agents"),  # (ValueError)
        (lambda w: {"actors": [w.actors[0], {"w": w.actors[0]["scale"]}]}, "weights: agent 1"),
        (lambda w: {"stats": {"wall_s": "long"}}, "weights: stats: 'wall_s' is not a number"),
        (lambda w: {"stats": {"counter": {"table_size": [1]}}}, "weights: stats: counter holds"),
        (lambda w: {"stats": {"bonus": {"bonus_mean": None}}}, "weights: stats: bonus holds"),
        (lambda w: {"stats": {1: 2}}, "weights: field 'stats' is not dict"),  # (AttributeError)
        (lambda w: {"unreported": ["2"]}, "weights: field 'unreported' is not list"),  # (TypeError)
    ],
)
def test_a_point_whose_weights_cannot_be_evaluated_is_refused_as_it_comes(spoil, why):
    """Checked in `handle`: the evaluation loop met them and raised, ending the process."""
    ev, _ = bare_evaluator()
    refused: list[str] = []
    ev.reject = lambda key, reason: refused.append(reason)  # type: ignore[method-assign]
    start(ev, ["r"])
    assign = Assignment.from_wire({"learner": "l", "actors": ["a0"]})
    ev.served.join("r", ev.active["r"], assign, {})  # (the run its messages are checked for)
    st = ev.runs["r"]
    assert isinstance(st.policy, LearnerPolicy)
    actors = weights_as_arrays(st.policy.learner.actor_weights())  # the learner's layout
    good = dataclasses.replace(point("r", 2), actors=actors)
    key = keys.k_weights("r", "eval")
    ev.handle("weights", key, encode(dataclasses.replace(good, **spoil(good))))
    assert len(refused) == 1 and refused[0].startswith(why) and not st.pending
    assert not ev.tick() and st.points == 0
    ev.handle("weights", key, encode(good))  # the same point's good weights: evaluated
    ev.tick()
    assert st.points == 1 and list(st.published) == [2] and len(refused) == 1
