"""The message codec: msgpack maps with a schema version, validated on the way in.

This is the only module that imports msgpack. Every message is one of
shared/net/messages.py's dataclasses, sent as a map with `v` (schema version), `type`,
`run` and its fields; numpy arrays travel as maps
{"nd": dtype, "shape": [...], "data": bytes} restricted to plain numeric dtypes
(never objects, never pickle), an `Assignment` as its `to_wire` map. `decode` checks
the version, the type, the presence and type of every field (a list's or a map's items
too: `_ITEMS`), array dtypes and shapes where the schema fixes them (a transitions
batch's values too: `_check_transitions`), and an assignment through
`Assignment.from_wire` (a `Resumed` through its own); anything else raises
`WireError`, which services count, log and drop.

A field with a default may be absent: a peer older than the field did not send it,
and the message is read with the default. A field typed `X | None` may be nil. An
older peer's `Status` carried its reason, final sequence number, points and resume in
its `detail` map: those keys are read into the fields (checked alike).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, TypeVar, overload

import msgpack
import numpy as np

from shared.net.messages import (
    MESSAGES,
    Assignment,
    BonusQuery,
    Message,
    Resumed,
    Transitions,
    WireError,
)

# 2: messages are shared/net/messages.py's dataclasses; the weights' incarnation and
# unreported points are fields of their own (version 1 carried them in its stats map).
SCHEMA_VERSION = 2
_DTYPES = {"<f4", "<f8", "<i8", "<i4", "|u1", "|b1"}
_NP_DTYPES = {d: np.dtype(d) for d in _DTYPES}

M = TypeVar("M", bound=Message)
# the field types sent as their `to_wire` map and read through their `from_wire`
_TYPED_CLASSES: dict[str, Any] = {"Assignment": Assignment, "Resumed": Resumed}


def _kind(annotation: str) -> Any:
    """The check of a field of type `annotation` (less its `| None`): a Python type,
    "nd" for an array, or a typed class (a map on the wire, read through its `from_wire`)."""
    annotation = annotation.removesuffix(" | None")
    if annotation == "np.ndarray":
        return "nd"
    if annotation in _TYPED_CLASSES:
        return _TYPED_CLASSES[annotation]
    base = annotation.split("[")[0]
    return {"str": str, "int": int, "dict": dict, "list": list}[base]


def _all_str_keys(value: dict) -> bool:
    return all(type(k) is str for k in value)


# A list or map field's items, by its annotation: what its readers take them for (a
# number compared, a name a string), so that, say, a stats map with an int key or an
# unreported point that is a string is refused here, not found out by a reader.
_ITEMS: dict[str, Any] = {
    "list[int]": lambda v: all(type(x) is int for x in v),
    "list[str]": lambda v: all(type(x) is str for x in v),
    "dict[str, int]": lambda v: all(type(k) is str and type(x) is int for k, x in v.items()),
    "dict[str, Any]": _all_str_keys,
    "list[dict[str, Any]]": lambda v: all(type(d) is dict and _all_str_keys(d) for d in v),
    "list[dict[str, np.ndarray]]": lambda v: all(
        type(d) is dict and all(type(k) is str and type(a) is np.ndarray for k, a in d.items())
        for d in v
    ),
}


def _items(annotation: str) -> tuple[str, Any] | None:
    """The check of a list or map field's items (`_ITEMS`), with the annotation it names."""
    annotation = annotation.removesuffix(" | None")
    if annotation.split("[")[0] not in ("list", "dict"):
        return None
    return annotation, _ITEMS[annotation]  # (a KeyError here: a new field's, to add)


# type -> {field: python type, "nd" for an ndarray, or a typed class}: what decode
# checks, from the dataclasses themselves.
SCHEMAS: dict[str, dict[str, Any]] = {
    type_: {f.name: _kind(str(f.type)) for f in dataclasses.fields(cls) if f.name != "run"}
    for type_, cls in MESSAGES.items()
}
# type -> {field: (its annotation, the check of its items)} for its list and map fields
_ITEM_CHECKS = {
    t: {f.name: items for f in dataclasses.fields(cls) if (items := _items(str(f.type)))}
    for t, cls in MESSAGES.items()
}
# type -> its fields that may be nil (typed `X | None`)
_NULLABLE = {
    t: {f.name for f in dataclasses.fields(cls) if str(f.type).endswith(" | None")}
    for t, cls in MESSAGES.items()
}
# type -> its fields that may be absent (they have a default: an older peer lacks them)
_OPTIONAL = {
    t: {
        f.name
        for f in dataclasses.fields(cls)
        if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING
    }
    for t, cls in MESSAGES.items()
}
# type -> its fields sent as their `to_wire` map (an assignment, a resume)
_TYPED = {
    t: [f for f, kind in s.items() if kind in _TYPED_CLASSES.values()] for t, s in SCHEMAS.items()
}
# the keys an older peer's status carried in its detail, now fields of their own
_STATUS_LIFTED = ("reason", "final_seq", "points", "resumed")


def _pack_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        arr = np.ascontiguousarray(obj)
        if arr.dtype.str not in _DTYPES:
            raise TypeError(f"dtype {arr.dtype} is not allowed on the wire")
        return {"nd": arr.dtype.str, "shape": list(arr.shape), "data": arr.tobytes()}
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    raise TypeError(f"cannot encode {type(obj).__name__}")


def _array(obj: dict) -> Any:
    """A map that is an array's encoding, as the array (WireError if malformed); any
    other map as it is. Called for every map of every inbound message (6 arrays in a
    transitions batch): dtype objects are looked up, not built, and the checks stay in
    plain loops."""
    if "nd" in obj and "data" in obj and "shape" in obj:
        dtype, shape, data = _NP_DTYPES.get(obj["nd"]), obj["shape"], obj["data"]
        if dtype is None or type(shape) is not list or type(data) is not bytes:
            raise WireError(f"bad array encoding: dtype {obj['nd']!r:.40}")
        for s in shape:
            if type(s) is not int or s < 0:
                raise WireError("bad array shape")
        if math.prod(shape) * dtype.itemsize != len(data):
            raise WireError("array data does not match its shape")
        return np.frombuffer(data, dtype=dtype).reshape(shape)
    return obj


# What one message may cost to decode. msgpack builds every map and list before a check
# here sees it, and an empty map is 1 byte on the wire and ~64 in memory: 8 MB of them
# took 550 MB. So a payload is refused past its type's size, each string, array's
# bytes, list and map past a length, and the decode stops once the maps, lists and their
# items (`_Budget`) outnumber what the payload's size allows.
MAX_STR = 1 << 20  # a string: a config's, a reason (a few KB)
MAX_BIN = 64 << 20  # an array's bytes (an actor's [4096, 4096] layer)
MAX_MAP = 1 << 14  # a map's entries: a config's, a stats map, an ack's actors (tens)
# A list's items: the longest is a history's rows, one per evaluation point (a thesis
# run of 50,000 episodes evaluated every one: 50,000); History's size binds first.
MAX_ARRAY = 1 << 18
SMALL_PAYLOAD = 4 << 20  # a message of any type not in MAX_PAYLOAD (a start: a few KB)
MAX_PAYLOAD = {
    "transitions": 256 << 20,  # an episode's rows (spread of 8 agents, 1,000 steps: 3 MB)
    "weights": 256 << 20,  # every agent's actor (8 agents of [400, 300]: 4.5 MB)
    "bonus_query": 64 << 20,  # a tick's minibatches (20 x 100 rows: < 1 MB)
    "bonus_reply": 64 << 20,
    "history": 64 << 20,  # rows of ~380 bytes: ~170,000 (50,000: 19 MB)
}
ITEMS_FREE = 1 << 16  # maps, lists and their items any message may have
# ...and one more per this many bytes, for a type whose size is in them (not in its
# arrays): a history's row is ~18 bytes per item (a map and its 20 entries in ~380).
ITEM_BYTES = 8
# The types whose size is in their arrays: their items are few whatever their size (a
# transitions batch: ~30; weights: ~60 per agent), so ITEMS_FREE is all they get.
_ARRAY_SIZED = {
    t
    for t, cls in MESSAGES.items()
    if any("np.ndarray" in str(f.type) for f in dataclasses.fields(cls))
}


class _Budget:
    """The maps, lists and items one decode may still build: msgpack's hooks charge
    each map and list (and its entries) as it is built; past the budget the decode
    stops with WireError, before the rest is built."""

    __slots__ = ("left",)

    def __init__(self, payload: int, type_: str | None) -> None:
        sized_by_items = type_ is None or type_ not in _ARRAY_SIZED
        self.left = ITEMS_FREE + (payload // ITEM_BYTES if sized_by_items else 0)

    def map(self, obj: dict) -> Any:
        self.left -= 1 + len(obj)
        if self.left < 0:
            raise WireError("too many maps and lists: more than the payload's size allows")
        return _array(obj)

    def list(self, obj: list) -> list:
        self.left -= 1 + len(obj)
        if self.left < 0:
            raise WireError("too many maps and lists: more than the payload's size allows")
        return obj


def encode(msg: Message) -> bytes:
    """Serialize a message; `decode` checks it against the same schema."""
    fields = {name: getattr(msg, name) for name in SCHEMAS[msg.TYPE]}
    for name in _TYPED[msg.TYPE]:
        if fields[name] is not None:
            fields[name] = fields[name].to_wire()
    body = {"v": SCHEMA_VERSION, "type": msg.TYPE, "run": msg.run, **fields}
    return msgpack.packb(body, default=_pack_default, use_bin_type=True)


@overload
def decode(payload: bytes, expect: type[M]) -> M: ...
@overload
def decode(payload: bytes, expect: None = None) -> Message: ...
def decode(payload: bytes, expect: type[Message] | None = None) -> Message:
    """Parse and validate into its message class (`expect`'s, or any); raises WireError
    for anything a service must not act on (past the limits above too, before it is
    built)."""
    expected = expect.TYPE if expect is not None else None
    cap = MAX_PAYLOAD.get(expected, SMALL_PAYLOAD) if expected else max(MAX_PAYLOAD.values())
    if len(payload) > cap:
        raise WireError(f"payload too large: {len(payload)} bytes, at most {cap}")
    budget = _Budget(len(payload), expected)
    try:
        msg = msgpack.unpackb(
            payload,
            object_hook=budget.map,
            list_hook=budget.list,
            raw=False,
            strict_map_key=False,
            max_str_len=MAX_STR,
            max_bin_len=MAX_BIN,
            max_array_len=MAX_ARRAY,
            max_map_len=MAX_MAP,
            max_ext_len=0,
        )
    except WireError:
        raise
    except Exception as err:  # msgpack raises several unrelated types
        raise WireError(f"undecodable payload: {type(err).__name__}") from None
    if not isinstance(msg, dict):
        raise WireError("message is not a map")
    if msg.get("v") != SCHEMA_VERSION:
        raise WireError(f"schema version: {msg.get('v')!r:.40}, expected {SCHEMA_VERSION}")
    type_ = msg.get("type")
    if type_ not in SCHEMAS or (expect is not None and type_ != expect.TYPE):
        raise WireError(f"unexpected message type: {type_!r:.40}")
    if not isinstance(msg.get("run"), str):
        raise WireError("message lacks a run id")
    if type_ == "status" and isinstance(msg.get("detail"), dict):
        _lift_status(msg)
    present = {}
    for field, kind in SCHEMAS[type_].items():
        if field not in msg:
            if field in _OPTIONAL[type_]:
                continue  # an older peer's: the dataclass's default
            raise WireError(f"{type_}: missing field {field!r}")
        value = present[field] = msg[field]
        if value is None and field in _NULLABLE[type_]:
            continue
        if kind == "nd":
            if not isinstance(value, np.ndarray):
                raise WireError(f"{type_}: field {field!r} is not an array")
        elif kind in _TYPED_CLASSES.values():
            try:
                present[field] = kind.from_wire(value)
            except WireError as err:
                raise WireError(f"{type_}: {err}") from None
        elif not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            raise WireError(f"{type_}: field {field!r} is not {kind.__name__}")
        elif field in _ITEM_CHECKS[type_] and not _ITEM_CHECKS[type_][field][1](value):
            raise WireError(f"{type_}: field {field!r} is not {_ITEM_CHECKS[type_][field][0]}")
    if type_ == "transitions":
        _check_transitions(msg)
    return MESSAGES[type_](run=msg["run"], **present)


def _lift_status(msg: dict) -> None:
    """An older peer's status: what it carried in `detail` that is now a field of its
    own goes there (unless the field came too), to be checked like any field."""
    detail = msg["detail"]
    for key in _STATUS_LIFTED:
        if key in detail and key not in msg:
            msg[key] = detail.pop(key)


# A transitions batch's columns as the actor sends them (services/actor/outbox.py) and
# the learner's log and replay store them: any other dtype is refused, not converted.
_TRANSITION_DTYPES = {
    "obs": np.dtype("<f4"),
    "act": np.dtype("<f4"),
    "rew": np.dtype("<f4"),
    "next_obs": np.dtype("<f4"),
    "done": np.dtype("<f4"),
    "collisions": np.dtype("<i4"),
}
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1  # the learner logs `policy_version` as int32


def _check_transitions(msg: dict) -> None:
    """What the counter and the learner take as a batch, whole: every column of its
    dtype and of n rows; finite values (a NaN reward or an inf next observation would
    go into replay and every update after it); `done` 0 or 1; no negative collision
    count; a `policy_version` the log's int32 column holds (one that overflowed it was
    taken, then failed to log: the actor resent it and the learner failed again)."""
    for field, dtype in _TRANSITION_DTYPES.items():
        if msg[field].dtype != dtype:
            raise WireError(f"transitions: {field} is {msg[field].dtype}, not {dtype}")
    if msg["rew"].ndim != 1 or len(msg["rew"]) == 0 or msg["seq"] < 0:
        raise WireError("transitions: empty batch or negative seq")
    n = len(msg["rew"])
    for field in ("obs", "act", "next_obs"):
        if msg[field].ndim != 2 or len(msg[field]) != n:
            raise WireError(f"transitions: {field} must be ({n}, dim)")
    for field in ("rew", "done", "collisions"):
        if msg[field].shape != (n,):
            raise WireError(f"transitions: {field} must be ({n},)")
    if msg["obs"].shape != msg["next_obs"].shape:
        raise WireError("transitions: obs and next_obs differ in shape")
    for field in ("obs", "act", "rew", "next_obs"):
        if not np.isfinite(msg[field]).all():
            raise WireError(f"transitions: non-finite values in {field}")
    done = msg["done"]
    if not ((done == 0) | (done == 1)).all():
        raise WireError("transitions: done is neither 0 nor 1")
    if (msg["collisions"] < 0).any():
        raise WireError("transitions: negative collisions")
    if not INT32_MIN <= msg["policy_version"] <= INT32_MAX:
        raise WireError("transitions: policy_version out of the int32 range")


def transitions_error(msg: Transitions) -> str | None:
    """Why the counter and the learner would refuse `msg` at decode (None: they take
    it): the sender's own check, so a world that gives a NaN is said, not resent."""
    try:
        _check_transitions(vars(msg))
    except WireError as err:
        return str(err)
    return None


def check_batch_rows(msg: Transitions, episode_len: int, lockstep: bool) -> None:
    """A run's batch is one episode (one step in lockstep), as actors publish them: the
    learner's replay takes nothing else, so the counter must not count anything else
    either (rows it counted that never reach replay, and the real ones for those
    numbers later dropped as duplicates, uncounted)."""
    n = len(msg)
    if n != (1 if lockstep else episode_len):
        what = "one step (lockstep)" if lockstep else f"one episode ({episode_len})"
        raise WireError(f"transitions: a batch is {what}, got {n}")


def check_dims(msg: Transitions | BonusQuery, obs_dim: int, act_dim: int) -> None:
    """The run's layout: a batch for another task's dimensions is refused (and a bonus
    query's non-finite rows; a batch's values were checked at decode)."""
    obs, act = msg.obs, msg.act
    if obs.shape[1] != obs_dim or act.shape[1] != act_dim:
        raise WireError(
            f"{msg.TYPE}: dims ({obs.shape[1]}, {act.shape[1]}), run has ({obs_dim}, {act_dim})"
        )
    if not (np.isfinite(obs).all() and np.isfinite(act).all()):
        raise WireError(f"{msg.TYPE}: non-finite values")
