"""The codec's array decoding and validation, in process: what every inbound message goes
through, so malformed arrays must be refused here whatever shortcuts the decoder takes;
and a run's `Assignment`, which a start carries as the same map as before it was typed."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from shared.net.messages import (
    MESSAGES,
    Ack,
    Assignment,
    Metrics,
    Start,
    Status,
    Stop,
    Transitions,
    Weights,
)
from shared.net.wire import SCHEMA_VERSION, SCHEMAS, WireError, check_dims, decode, encode


def _transitions(n: int = 3, obs_dim: int = 4, act_dim: int = 2, **over) -> dict:
    rng = np.random.default_rng(0)
    obs = rng.standard_normal((n, obs_dim)).astype(np.float32)
    fields = {
        "actor": "a0",
        "seq": 0,
        "obs": obs,
        "act": rng.standard_normal((n, act_dim)).astype(np.float32),
        "rew": np.zeros(n, np.float32),
        "next_obs": obs,
        "done": np.zeros(n, np.float32),
        "collisions": np.zeros(n, np.int32),
        "policy_version": 0,
    }
    return {**fields, **over}


def _raw(msg_fields: dict) -> dict:
    """The message as a plain msgpack map, to be tampered with."""
    return msgpack.unpackb(encode(Transitions("r", **msg_fields)), raw=False)


def _repack(raw: dict) -> bytes:
    return msgpack.packb(raw, use_bin_type=True)


def test_round_trip_keeps_dtypes_shapes_and_values():
    fields = _transitions()
    msg = decode(encode(Transitions("r", **fields)), Transitions)
    assert isinstance(msg, Transitions) and msg.run == "r" and len(msg) == 3
    for name in ("obs", "act", "rew", "next_obs", "done", "collisions"):
        assert getattr(msg, name).dtype == fields[name].dtype
        assert np.array_equal(getattr(msg, name), fields[name])
    assert (msg.actor, msg.seq, msg.policy_version) == ("a0", 0, 0)
    check_dims(msg, 4, 2)


@pytest.mark.parametrize(
    "tamper",
    [
        lambda a: a.update(nd="|O"),  # object arrays never
        lambda a: a.update(nd="<f2"),  # not an allowed dtype
        lambda a: a.update(nd=["<f4"]),  # not even a string
        lambda a: a.update(shape=[3, -4]),
        lambda a: a.update(shape=[3, 4.0]),
        lambda a: a.update(shape=[3, True]),
        lambda a: a.update(shape="3,4"),
        lambda a: a.update(shape=[3, 5]),  # data does not fill the shape
        lambda a: a.update(data=a["data"][:-1]),
        lambda a: a.update(data="text"),
    ],
)
def test_malformed_arrays_are_refused(tamper):
    raw = _raw(_transitions())
    tamper(raw["obs"])
    with pytest.raises(WireError):
        decode(_repack(raw), Transitions)


def test_shapes_that_disagree_with_the_batch_are_refused():
    with pytest.raises(WireError):
        decode(encode(Transitions("r", **_transitions(rew=np.zeros(2, np.float32)))))
    with pytest.raises(WireError):
        decode(encode(Transitions("r", **_transitions(act=np.zeros((3,), np.float32)))))
    msg = decode(encode(Transitions("r", **_transitions())))
    with pytest.raises(WireError):
        check_dims(msg, 5, 2)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("field", ["obs", "act"])
def test_non_finite_values_are_refused(field, bad):
    fields = _transitions()
    arr = fields[field].copy()
    arr[1, 0] = bad
    msg = decode(encode(Transitions("r", **{**fields, field: arr})))
    with pytest.raises(WireError, match="non-finite"):
        check_dims(msg, 4, 2)


def test_large_finite_values_pass():
    fields = _transitions()
    obs = np.full_like(fields["obs"], np.finfo(np.float32).max)
    msg = decode(encode(Transitions("r", **{**fields, "obs": obs, "next_obs": obs})))
    check_dims(msg, 4, 2)


def test_a_map_that_only_looks_like_an_array_stays_a_map():
    # "nd" without "shape"/"data" is ordinary data (e.g. in a metrics map), not an array.
    payload = encode(Metrics("r", source="s", data={"nd": "<f4", "x": 1}))
    assert decode(payload, Metrics).data == {"nd": "<f4", "x": 1}


def test_every_message_type_round_trips_as_its_class():
    weights = Weights(
        "r",
        version=3,
        updates=7,
        env_steps=20,
        episodes=1,
        eval_point=1,
        collisions_cum=0,
        actors=[{"w": np.ones((2, 2), np.float32)}],
        stats={"wall_s": 1.5},
        incarnation="learner:1:2",
        unreported=[0],
    )
    msg = decode(encode(weights), Weights)
    assert (msg.version, msg.incarnation, msg.unreported, msg.stats) == (
        3,
        "learner:1:2",
        [0],
        {"wall_s": 1.5},
    )
    assert np.array_equal(msg.actors[0]["w"], np.ones((2, 2), np.float32))
    assert decode(encode(Stop("r", reason="x"))) == Stop("r", reason="x")
    assert decode(encode(Ack("r", service="c", acked={"a0": 4}, window=0)), Ack).acked == {"a0": 4}
    assert set(MESSAGES) == set(SCHEMAS)


def test_a_message_of_another_type_or_lacking_a_field_is_refused():
    payload = encode(Stop("r", reason="x"))
    with pytest.raises(WireError, match="unexpected message type"):
        decode(payload, Status)
    raw = msgpack.unpackb(encode(Status("r", service="s", state="running", detail={})), raw=False)
    del raw["detail"]
    with pytest.raises(WireError, match="missing field 'detail'"):
        decode(_repack(raw), Status)
    raw = msgpack.unpackb(payload, raw=False)
    raw["v"] = SCHEMA_VERSION - 1  # the version before: its weights carried other fields
    with pytest.raises(WireError, match="schema version"):
        decode(_repack(raw))


# ---------------------------------------------------------------- the assignment
RUN = {"counter": "c0", "learner": "L", "evaluator": "E", "actors": ["a0", "a1"]}
GROUP = {"counter": "c0", "learner": "L", "evaluator": "E", "actors": ["a0"], "group": ["g0", "g1"]}


@pytest.mark.parametrize("wire", [RUN, GROUP, {"learner": "L", "actors": ["a0"]}])
def test_an_assignment_round_trips_as_its_map(wire):
    assign = Assignment.from_wire(wire)
    assert assign.to_wire() == wire and Assignment.from_wire(assign.to_wire()) == assign
    assert list(assign.to_wire()) == list(wire)  # the keys in the order they were sent


def test_an_assignment_names_its_services_by_role():
    run, group = Assignment.from_wire(RUN), Assignment.from_wire(GROUP)
    assert run.names("learner", "L") and run.names("counter", "c0") and run.names("evaluator", "E")
    assert (
        run.names("actor", "a1") and not run.names("actor", "L") and not run.names("learner", "a0")
    )
    assert not run.names("service", "L") and not run.names("actors", "a0")
    assert run.services() == [
        ("counter", "c0"), ("learner", "L"), ("evaluator", "E"), ("actor", "a0"), ("actor", "a1")
    ]  # fmt: skip
    assert run.held() == {"L", "E", "a0", "a1"}  # the counter serves many runs
    assert group.group == ("g0", "g1") and run.group is None
    alone = Assignment.from_wire({"learner": "L", "actors": ["a0"]})
    assert alone.services() == [("learner", "L"), ("actor", "a0")] and alone.counter is None


@pytest.mark.parametrize(
    "change, field, why",
    [
        ({"learner": None}, "learner", "is missing"),
        ({"actors": None}, "actors", "is missing"),
        ({"learner": ""}, "learner", "is not a service id"),
        ({"learner": 3}, "learner", "is not a service id"),
        ({"counter": ["c0"]}, "counter", "is not a service id"),
        ({"evaluator": 1.5}, "evaluator", "is not a service id"),
        ({"actors": "a0"}, "actors", "is not a non-empty list"),
        ({"actors": []}, "actors", "is not a non-empty list"),
        ({"actors": ["a0", 1]}, "actors", "holds something other than an id"),
        ({"actors": ["a0", "a0"]}, "actors", "names an id twice"),
        ({"group": {"g0": 0}}, "group", "is not a non-empty list"),
        ({"group": ["g0", ""]}, "group", "holds something other than an id"),
        ({"group": ["g0", "g0"]}, "group", "names an id twice"),
        ({"actor": "a0"}, "actor", "unknown field"),
    ],
)
def test_a_malformed_assignment_is_refused_naming_the_field(change, field, why):
    wire = {k: v for k, v in {**GROUP, **change}.items() if v is not None or k not in change}
    if why == "unknown field":
        match = f"assignment: unknown field {field!r}"
    else:
        match = f"assignment: field {field!r} {why}"
    with pytest.raises(WireError, match=match):
        Assignment.from_wire(wire)


def test_an_assignment_that_is_no_map_is_refused():
    for bad in (None, ["L"], "L"):
        with pytest.raises(WireError, match="assignment: not a map"):
            Assignment.from_wire(bad)
    none = Assignment.from_wire({**RUN, "counter": None, "evaluator": None})  # null: none named
    assert none.counter is None and none.evaluator is None


@pytest.mark.parametrize("assign", [RUN, GROUP])
def test_a_start_sent_before_the_assignment_was_typed_decodes_and_encodes_the_same(assign):
    # A start as the code before Assignment sent it: its assignment a plain map.
    config = {"task": "speaker_listener", "k": 32}
    body = {"v": SCHEMA_VERSION, "type": "start", "run": "g0", "config": config, "assign": assign}
    before = msgpack.packb(body, use_bin_type=True)
    start = decode(before, Start)
    assert start.assign == Assignment.from_wire(assign) and start.assign.learner == "L"
    assert msgpack.unpackb(encode(start), raw=False) == body
    assert encode(start) == before  # the same bytes: nothing on the wire changed


def test_a_start_with_a_malformed_assignment_is_refused_naming_the_field():
    raw = msgpack.unpackb(
        encode(Start("r", config={}, assign=Assignment.from_wire(RUN))), raw=False
    )
    raw["assign"]["actors"] = "a0"
    with pytest.raises(WireError, match="start: assignment: field 'actors' is not a non-empty"):
        decode(_repack(raw), Start)
    del raw["assign"]
    with pytest.raises(WireError, match="missing field 'assign'"):
        decode(_repack(raw), Start)
