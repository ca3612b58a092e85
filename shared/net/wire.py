"""The message codec: msgpack maps with a schema version, validated on the way in.

This is the only module that imports msgpack. Every message is one of
shared/net/messages.py's dataclasses, sent as a map with `v` (schema version), `type`,
`run` and its fields; numpy arrays travel as maps
{"nd": dtype, "shape": [...], "data": bytes} restricted to plain numeric dtypes
(never objects, never pickle), an `Assignment` as its `to_wire` map. `decode` checks
the version, the type, the presence and type of every field, array dtypes and shapes
where the schema fixes them, and an assignment through `Assignment.from_wire` (a
`Resumed` through its own); anything else raises `WireError`, which services count,
log and drop.

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


# type -> {field: python type, "nd" for an ndarray, or a typed class}: what decode
# checks, from the dataclasses themselves.
SCHEMAS: dict[str, dict[str, Any]] = {
    type_: {f.name: _kind(str(f.type)) for f in dataclasses.fields(cls) if f.name != "run"}
    for type_, cls in MESSAGES.items()
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


def _unpack_hook(obj: dict) -> Any:
    # Called for every map of every inbound message (6 arrays in a transitions batch):
    # dtype objects are looked up, not built, and the checks stay in plain loops.
    if "nd" in obj and "data" in obj and "shape" in obj:
        dtype, shape, data = _NP_DTYPES.get(obj["nd"]), obj["shape"], obj["data"]
        if dtype is None or type(shape) is not list or type(data) is not bytes:
            raise WireError(f"bad array encoding (dtype {obj['nd']!r})")
        for s in shape:
            if type(s) is not int or s < 0:
                raise WireError("bad array shape")
        if math.prod(shape) * dtype.itemsize != len(data):
            raise WireError("array data does not match its shape")
        return np.frombuffer(data, dtype=dtype).reshape(shape)
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
    for anything a service must not act on."""
    try:
        msg = msgpack.unpackb(
            payload, object_hook=_unpack_hook, raw=False, strict_map_key=False, max_bin_len=64 << 20
        )
    except WireError:
        raise
    except Exception as err:  # msgpack raises several unrelated types
        raise WireError(f"undecodable payload: {type(err).__name__}") from None
    if not isinstance(msg, dict):
        raise WireError("message is not a map")
    if msg.get("v") != SCHEMA_VERSION:
        raise WireError(f"schema version {msg.get('v')!r}, expected {SCHEMA_VERSION}")
    type_ = msg.get("type")
    if type_ not in SCHEMAS or (expect is not None and type_ != expect.TYPE):
        raise WireError(f"unexpected message type {type_!r}")
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


def _check_transitions(msg: dict) -> None:
    n = len(msg["rew"])
    if msg["seq"] < 0 or n == 0:
        raise WireError("transitions: empty batch or negative seq")
    for field in ("obs", "act", "next_obs"):
        if msg[field].ndim != 2 or len(msg[field]) != n:
            raise WireError(f"transitions: {field} must be ({n}, dim)")
    for field in ("rew", "done", "collisions"):
        if msg[field].shape != (n,):
            raise WireError(f"transitions: {field} must be ({n},)")
    if msg["obs"].shape != msg["next_obs"].shape:
        raise WireError("transitions: obs and next_obs differ in shape")


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
    """The run's layout: a batch for another task's dimensions is refused."""
    obs, act = msg.obs, msg.act
    if obs.shape[1] != obs_dim or act.shape[1] != act_dim:
        raise WireError(
            f"{msg.TYPE}: dims ({obs.shape[1]}, {act.shape[1]}), run has ({obs_dim}, {act_dim})"
        )
    if not (np.isfinite(obs).all() and np.isfinite(act).all()):
        raise WireError(f"{msg.TYPE}: non-finite values")
