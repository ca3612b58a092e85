"""The codec's array decoding and validation, in process: what every inbound message goes
through, so malformed arrays must be refused here whatever shortcuts the decoder takes;
and a run's `Assignment`, which a start carries as the same map as before it was typed."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from shared.net.messages import (
    MAX_ID_BYTES,
    MESSAGES,
    Ack,
    Assignment,
    BonusQuery,
    BonusReply,
    History,
    Metrics,
    Resumed,
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
        ({"actors": ["a0", "a" * 256]}, "actors", "holds something other than an id"),
        ({"counter": "é" * 128}, "counter", "is not a service id"),  # 256 bytes
        ({"group": {"g0": 0}}, "group", "is not a non-empty list"),
        ({"group": ["g0", ""]}, "group", "holds something other than an id"),
        ({"group": ["g0", "g0"]}, "group", "names an id twice"),
        ({"actor": "a0"}, "actor", "unknown field"),
    ],
)
def test_a_malformed_assignment_is_refused_naming_the_field(change, field, why):
    """(An id is at most MAX_ID_BYTES bytes: ids go into keys and the counter's log,
    whose records hold an actor's id after a 2-byte length.)"""
    wire = {k: v for k, v in {**GROUP, **change}.items() if v is not None or k not in change}
    if why == "unknown field":
        match = f"assignment: unknown field {field!r}"
    else:
        match = f"assignment: field {field!r} {why}"
    with pytest.raises(WireError, match=match):
        Assignment.from_wire(wire)


def test_an_id_of_the_longest_length_is_one():
    longest = "é" * (MAX_ID_BYTES // 2) + "a"  # 255 bytes
    assert Assignment.from_wire({"learner": longest, "actors": [longest]}).learner == longest


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
    assert start.attempt is None  # (no attempt then either: a field added since)
    now = {**body, "attempt": None}
    assert msgpack.unpackb(encode(start), raw=False) == now
    assert encode(start) == msgpack.packb(now, use_bin_type=True)  # the assignment's bytes kept


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


# ---------------------------------------------------------------- a status's fields
RESUMED = Resumed("r", from_episode=40, updates=9, replay_rows=120, held_batches=0, seconds=0.5)


def test_a_status_round_trips_its_typed_fields():
    msg = Status(
        "r", service="L", state="completed", detail={"rank": 0}, final_seq=7, resumed=RESUMED
    )
    back = decode(encode(msg), Status)
    assert back == msg and back.resumed is not None and back.resumed.from_episode == 40
    assert back.fields() == {"rank": 0, "final_seq": 7, "resumed": RESUMED.to_wire()}
    grouped = RESUMED.grouped(["g0", "g1"])
    assert decode(encode(Status("g0", "L", "running", {}, resumed=grouped))).resumed == grouped


@pytest.mark.parametrize(
    "old, field, value",
    [
        ({"final_seq": 12, "episodes": 4}, "final_seq", 12),
        ({"points": 3}, "points", 3),
        ({"reason": "learner failed: x"}, "reason", "learner failed: x"),
        ({"resumed": RESUMED.to_wire()}, "resumed", RESUMED),
        ({"resumed": {**RESUMED.to_wire(), "from_episode": None}}, "resumed", None),
    ],
)
def test_an_older_peers_status_is_read_into_the_fields(old, field, value):
    """A peer from before the fields sent them in `detail` (and no key of its own):
    read into the fields, off the detail, so a reader sees one form."""
    raw = {"v": SCHEMA_VERSION, "type": "status", "run": "r", "service": "a0"}
    msg = decode(_repack({**raw, "state": "completed", "detail": dict(old)}), Status)
    if field == "resumed" and value is None:  # a resume from the log alone: no cut
        assert msg.resumed is not None and msg.resumed.from_episode is None
    else:
        assert getattr(msg, field) == value
    assert field not in msg.detail and msg.fields() == {**old, **msg.fields()}
    assert msg.detail == {k: v for k, v in old.items() if k != field}


@pytest.mark.parametrize(
    "change, why",
    [
        ({"final_seq": "12"}, "field 'final_seq' is not int"),
        ({"final_seq": True}, "field 'final_seq' is not int"),
        ({"detail": {"points": 2.5}}, "field 'points' is not int"),  # (an old form, malformed)
        ({"reason": 3}, "field 'reason' is not str"),
        ({"resumed": {"run": "r"}}, "resumed: field 'updates' is not int"),
        ({"resumed": [1]}, "resumed: not a map"),
        ({"detail": None}, "field 'detail' is not dict"),
    ],
)
def test_a_malformed_status_is_refused_naming_the_field(change, why):
    raw = msgpack.unpackb(encode(Status("r", "a0", "completed", {})), raw=False)
    if "detail" in change:  # an older peer's form: no key of the fields' own
        raw = {k: v for k, v in raw.items() if k not in ("reason", "final_seq", "points")}
    with pytest.raises(WireError, match=why):
        decode(_repack({**raw, **change}), Status)


def test_a_status_without_the_newer_fields_reads_them_as_unset():
    raw = {"v": SCHEMA_VERSION, "type": "status", "run": "r", "service": "e", "state": "running"}
    msg = decode(_repack({**raw, "detail": {"rank": 1}}), Status)
    assert (msg.reason, msg.final_seq, msg.points, msg.resumed) == (None, None, None, None)
    assert msg.fields() == {"rank": 1}


@pytest.mark.parametrize("cls", [Metrics, History])
def test_metrics_and_history_name_their_attempt_and_an_older_peers_without_one_decode(cls):
    """A row names the attempt of the run it is of (a retried run's reader drops an ended
    attempt's); one from a peer before the field decodes as naming none."""
    fields = {"source": "eval", "data": {"episode": 4}} if cls is Metrics else {
        "source": "eval", "rows": [{"episode": 4}], "state": "running"}  # fmt: skip
    msg = cls("r", **fields, attempt=2)
    assert decode(encode(msg), cls) == msg
    before = {"v": SCHEMA_VERSION, "type": cls.TYPE, "run": "r", **fields}
    assert decode(msgpack.packb(before, use_bin_type=True), cls).attempt is None
    with pytest.raises(WireError, match=f"{cls.TYPE}: field 'attempt' is not int"):
        decode(msgpack.packb({**before, "attempt": "2"}, use_bin_type=True), cls)


def test_acks_and_bonus_messages_name_attempt_and_counter_and_an_older_peers_decode():
    """Ack.attempt, BonusQuery.attempt and BonusReply.service are optional: a peer from
    before them sends none and is read as naming none (taken as before)."""
    rows = np.zeros((2, 3), np.float32)
    msgs = [
        Ack("r", service="c0", acked={"a0": 5}, window=0, attempt=2),
        BonusQuery("r", obs=rows, act=rows, attempt=2),
        BonusReply("r", counts=np.ones((1, 2), np.int64), bonus=rows[:, :2], service="c0"),
    ]
    for msg, field in zip(msgs, ("attempt", "attempt", "service")):
        back = decode(encode(msg), type(msg))
        assert getattr(back, field) == getattr(msg, field)
        raw = msgpack.unpackb(encode(msg), raw=False)
        del raw[field]
        assert getattr(decode(_repack(raw), type(msg)), field) is None
