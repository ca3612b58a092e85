"""The codec's array decoding and validation, in process: what every inbound message goes
through, so malformed arrays must be refused here whatever shortcuts the decoder takes."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from shared.net.messages import MESSAGES, Ack, Metrics, Status, Stop, Transitions, Weights
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
