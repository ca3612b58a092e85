"""The message codec: msgpack maps with a schema version, validated on the way in.

This is the only module that imports msgpack. Every message is a map with
`v` (schema version), `type` and `run`; numpy arrays travel as maps
{"nd": dtype, "shape": [...], "data": bytes} restricted to plain numeric dtypes
(never objects, never pickle). `decode` checks the version, the type, the presence
and type of every field, and array dtypes and shapes where the schema fixes them;
anything else raises `WireError`, which services count, log and drop.
"""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np

SCHEMA_VERSION = 1
_DTYPES = {"<f4", "<f8", "<i8", "<i4", "|u1", "|b1"}
_NP_DTYPES = {d: np.dtype(d) for d in _DTYPES}

# type -> {field: python type(s)}; "nd" marks an ndarray field.
SCHEMAS: dict[str, dict[str, Any]] = {
    # actor -> counter, learner: a batch of numbered training transitions
    "transitions": {
        "actor": str,  # service id of the actor
        "seq": int,  # number of the first transition in the batch (0-based, per actor)
        "obs": "nd",  # (n, joint_obs) float32
        "act": "nd",  # (n, joint_act) float32
        "rew": "nd",  # (n,) float32, extrinsic
        "next_obs": "nd",
        "done": "nd",  # (n,) float32
        "collisions": "nd",  # (n,) int32
        "policy_version": int,  # weights version that chose these actions
    },
    # counter/learner -> actors: next expected seq per actor; window = credits (learner)
    "ack": {"service": str, "acked": dict, "window": int},
    # learner -> actors, evaluator: actor weights (latest only matters)
    "weights": {
        "version": int,
        "updates": int,
        "env_steps": int,
        "episodes": int,
        "eval_point": int,  # episode number to evaluate at, or -1
        "collisions_cum": int,
        "actors": list,  # per agent: {param name: ndarray}
        "info": dict,  # learner stats at this point (replay_ratio, policy_lag, wall_s, ...)
    },
    # interleave lockstep (central inference): actor -> learner, the observation its
    # step `seq` acts on; the learner answers once every step before it is learnt
    "act_request": {"actor": str, "seq": int, "obs": "nd"},  # obs (joint_obs,) float32
    # learner -> that actor: the policy's action for step `seq` (noise is the actor's)
    "action": {"seq": int, "act": "nd"},  # (joint_act,) float32
    "bonus_query": {"obs": "nd", "act": "nd"},
    "bonus_reply": {"counts": "nd", "bonus": "nd"},
    # any service -> watchers: a metric point or stats
    "metrics": {"source": str, "data": dict},
    # evaluator -> API (reply to a history get): every row published for the run so far
    "history": {"source": str, "rows": list, "state": str},
    # run control
    "start": {"config": dict, "assign": dict},
    "stop": {"reason": str},
    "status": {"service": str, "state": str, "detail": dict},
}


class WireError(ValueError):
    """A message that must be dropped: undecodable, wrong version, wrong shape."""


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


def encode(type_: str, run: str, **fields: Any) -> bytes:
    """Build and serialize a message; the same schema `decode` enforces."""
    if type_ not in SCHEMAS:
        raise ValueError(f"unknown message type {type_!r}")
    missing = set(SCHEMAS[type_]) - set(fields)
    if missing:
        raise ValueError(f"{type_} message lacks {sorted(missing)}")
    msg = {"v": SCHEMA_VERSION, "type": type_, "run": run, **fields}
    return msgpack.packb(msg, default=_pack_default, use_bin_type=True)


def decode(payload: bytes, expect: str | None = None) -> dict[str, Any]:
    """Parse and validate; raises WireError for anything a service must not act on."""
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
    if type_ not in SCHEMAS or (expect is not None and type_ != expect):
        raise WireError(f"unexpected message type {type_!r}")
    if not isinstance(msg.get("run"), str):
        raise WireError("message lacks a run id")
    for field, kind in SCHEMAS[type_].items():
        if field not in msg:
            raise WireError(f"{type_}: missing field {field!r}")
        value = msg[field]
        if kind == "nd":
            if not isinstance(value, np.ndarray):
                raise WireError(f"{type_}: field {field!r} is not an array")
        elif not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            raise WireError(f"{type_}: field {field!r} is not {kind.__name__}")
    if type_ == "transitions":
        _check_transitions(msg)
    return msg


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


def check_dims(msg: dict, obs_dim: int, act_dim: int) -> None:
    """The run's layout: a batch for another task's dimensions is refused."""
    obs, act = msg["obs"], msg["act"]
    if obs.shape[1] != obs_dim or act.shape[1] != act_dim:
        raise WireError(
            f"{msg['type']}: dims ({obs.shape[1]}, {act.shape[1]}), run has ({obs_dim}, {act_dim})"
        )
    if not (np.isfinite(obs).all() and np.isfinite(act).all()):
        raise WireError(f"{msg['type']}: non-finite values")
