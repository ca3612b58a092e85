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
@pytest.mark.parametrize("field", ["obs", "act", "rew", "next_obs"])
def test_non_finite_values_are_refused(field, bad):
    """In every float column: a NaN reward or an inf next observation went into replay."""
    fields = _transitions()
    arr = fields[field].copy()
    arr.flat[1] = bad
    with pytest.raises(WireError, match=f"non-finite values in {field}"):
        decode(encode(Transitions("r", **{**fields, field: arr})), Transitions)
    query = BonusQuery("r", obs=fields["obs"], act=fields["act"])
    arr = fields["obs"].copy()
    arr[1, 0] = bad
    with pytest.raises(WireError, match="non-finite"):  # a bonus query's rows: by check_dims
        check_dims(decode(encode(BonusQuery("r", obs=arr, act=query.act))), 4, 2)


@pytest.mark.parametrize(
    "change, why",
    [
        ({"obs": np.zeros((3, 4)), "next_obs": np.zeros((3, 4))}, "obs is float64, not float32"),
        ({"act": np.zeros((3, 2), np.int32)}, "act is int32, not float32"),
        ({"rew": np.zeros(3, np.int64)}, "rew is int64, not float32"),
        ({"done": np.zeros(3, bool)}, "done is bool, not float32"),
        # float collisions (NaN among them) made the learner's ack path raise
        ({"collisions": np.array([0, np.nan, 1], np.float32)}, "collisions is float32, not"),
        ({"collisions": np.zeros(3, np.int64)}, "collisions is int64, not int32"),
        ({"done": np.array([0, 0.5, 1], np.float32)}, "done is neither 0 nor 1"),
        ({"done": np.array([0, 2, 1], np.float32)}, "done is neither 0 nor 1"),
        ({"collisions": np.array([0, -1, 0], np.int32)}, "negative collisions"),
        # the learner's log holds it as int32: it overflowed after the batch was taken
        ({"policy_version": 2**31}, "policy_version out of the int32 range"),
        ({"policy_version": -(2**31) - 1}, "policy_version out of the int32 range"),
        ({"rew": np.zeros(0, np.float32)}, "empty batch"),
        ({"rew": "0-d"}, "empty batch"),  # (len() of it raised TypeError, not WireError)
    ],
)
def test_a_batch_the_learner_cannot_take_whole_is_refused_at_decode(change, why):
    if isinstance(change.get("rew"), str):  # (encode sends arrays of one dimension or more)
        raw = _raw(_transitions())
        raw["rew"].update(shape=[], data=raw["rew"]["data"][:4])
        payload = _repack(raw)
    else:
        payload = encode(Transitions("r", **_transitions(**change)))
    with pytest.raises(WireError, match=why):
        decode(payload, Transitions)


def test_the_edges_of_a_batchs_values_pass():
    fields = _transitions(
        done=np.array([0, 1, 1], np.float32),
        collisions=np.array([0, 7, 2**31 - 1], np.int32),
        policy_version=2**31 - 1,
    )
    assert decode(encode(Transitions("r", **fields)), Transitions).policy_version == 2**31 - 1
    lockstep = decode(encode(Transitions("r", **{**fields, "policy_version": -1})))
    assert lockstep.policy_version == -1  # (a lockstep actor loads no weights: version -1)


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


@pytest.mark.parametrize(
    "msg, field, value",
    [
        (Ack("r", service="c", acked={"a0": 4}, window=0), "acked", {"a0": "4"}),
        (Ack("r", service="c", acked={"a0": 4}, window=0), "acked", {"a0": True}),
        (Ack("r", service="c", acked={"a0": 4}, window=0), "acked", {0: 4}),
        (Metrics("r", source="s", data={"x": 1}), "data", {1: 2}),
        (History("r", source="eval", rows=[{"episode": 1}], state="running"), "rows", [3]),
        (History("r", source="eval", rows=[{"episode": 1}], state="running"), "rows", [{1: 1}]),
        (Stop("r", reason="x"), None, None),  # (no list or map field: nothing to spoil)
    ],
)
def test_the_items_of_a_list_or_map_field_are_of_its_type(msg, field, value):
    """A map's names are strings and a list's or map's items what its annotation says
    (a stats map named by an int made the evaluator's row raise; a point that is a
    string, its point order): refused at decode, naming the field."""
    assert decode(encode(msg), type(msg)) == msg
    if field is None:
        return
    raw = msgpack.unpackb(encode(msg), raw=False, strict_map_key=False)
    with pytest.raises(WireError, match=f"{msg.TYPE}: field {field!r} is not"):
        decode(_repack({**raw, field: value}), type(msg))


# ---------------------------------------------------------------- what a decode may cost
def _history_of(rows: int) -> History:
    """A history of `rows` evaluation rows as the evaluator makes them (eval_row, with a
    beta schedule's column): a thesis run of 50,000 episodes evaluated every one."""
    from services.evaluator.points import eval_row
    from shared.config import make_config
    from shared.net.stats import LearnerStats
    from shared.run.rollout import EvalResult

    schedule = {"kind": "linear", "end": 0.1, "horizon": 20000, "unit": "episodes"}
    cfg = make_config({"task": "speaker_listener", "beta_schedule": schedule})
    stats = LearnerStats(
        counter={"table_size": 123456, "count1_pct": 12.5, "counted_transitions": 1234567},
        bonus={"bonus_mean": 0.1, "bonus_std": 0.2, "sampled_count1_pct": 3.3},
        wall_s=1234.5, steps_per_sec=345.6, replay_ratio=1.0, policy_lag=0.5,
    ).to_wire()  # fmt: skip
    ev = EvalResult(0.3, -12.345678, 10, 250)
    out = []
    for e in range(1, rows + 1):
        w = Weights("r", version=e, updates=20 * e, env_steps=25 * e, episodes=e, eval_point=e,
                    collisions_cum=3 * e, actors=[], stats=stats, incarnation="L:1:2")  # fmt: skip
        out.append(eval_row(w, ev, cfg))
    return History("r", source="eval", rows=out, state="running", attempt=1)


def _largest_weights(hidden: list[int]) -> Weights:
    """Weights of spread's 8 agents (the most the config allows; obs 48 each)."""
    from shared.config import make_config
    from shared.core.networks import JointPolicy, actor_weights
    from shared.envs.tasks import task_spec_for

    spec = task_spec_for(make_config({"task": "spread", "agents": 8}))
    actors = actor_weights(JointPolicy.for_task(spec, hidden).actors)
    stats = {"wall_s": 1.0, "counter": {"table_size": 1, "acked": {"a0": 5}}, "bonus": {}}
    return Weights("r", version=1, updates=2, env_steps=3, episodes=4, eval_point=4,
                   collisions_cum=0, actors=actors, stats=stats, incarnation="L:1:2",
                   unreported=list(range(0, 4000, 4)))  # fmt: skip


@pytest.mark.parametrize(
    "make",
    [
        lambda: _history_of(50_000),
        lambda: _largest_weights([400, 300]),  # the thesis's layers
        lambda: _largest_weights([256, 256]),
        lambda: Transitions("r", **_transitions(n=1000, obs_dim=384, act_dim=16)),
    ],
    ids=[
        "history-50000-rows",
        "weights-8x[400,300]",
        "weights-8x[256,256]",
        "transitions-1000x384",
    ],
)
def test_the_largest_real_messages_decode(make):
    msg = make()
    back = decode(encode(msg), type(msg))
    assert back.run == "r"
    if isinstance(msg, History):
        assert len(back.rows) == 50_000 and back.rows[-1] == msg.rows[-1]
    if isinstance(msg, Weights):
        assert all(np.array_equal(a[k], b[k]) for a, b in zip(msg.actors, back.actors) for k in a)


def _nested_empty_maps(size: int) -> bytes:
    """`size` bytes of lists of 255 empty maps each (one byte each on the wire, ~64 in
    memory): under every length limit, so only the decode's budget stops it."""
    inner = b"\xdc" + (255).to_bytes(2, "big") + b"\x80" * 255
    count = size // len(inner)
    return b"\xdd" + count.to_bytes(4, "big") + inner * count


@pytest.mark.parametrize("cls", [Status, Weights, History])
def test_a_payload_that_decodes_into_far_more_than_its_size_is_refused_early(cls):
    """4 MB of empty maps took ~280 MB before any check saw them (8 MB: 550 MB)."""
    import tracemalloc

    payload = _nested_empty_maps((4 << 20) - 64)
    tracemalloc.start()
    try:
        with pytest.raises(WireError, match="too many maps and lists"):
            decode(payload, cls)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 48 << 20, f"{peak / 2**20:.0f} MiB"


def test_what_no_message_holds_is_refused_before_it_is_built():
    flat = b"\xdd" + (8 << 20).to_bytes(4, "big") + b"\x80" * (8 << 20)  # 8M maps in one list
    with pytest.raises(WireError, match="undecodable payload: ValueError"):
        decode(flat, History)
    with pytest.raises(WireError, match="payload too large: 4194305 bytes"):  # a status: 4 MiB
        decode(b"\x00" * ((4 << 20) + 1), Status)
    raw = msgpack.unpackb(encode(Stop("r", reason="x")), raw=False)
    ext = msgpack.packb({**raw, "reason": msgpack.ExtType(1, b"x")})  # (no message has one)
    with pytest.raises(WireError, match="undecodable payload"):
        decode(ext, Stop)
    long = msgpack.packb({**raw, "reason": "x" * ((1 << 20) + 1)})
    with pytest.raises(WireError, match="undecodable payload"):
        decode(long, Stop)


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
