"""The messages on the bus, one frozen dataclass each.

A transition's path reads as types: the actor sends `Transitions` (or, in lockstep, an
`ActRequest` the learner answers with an `Action`); the counter and the learner each
answer with an `Ack`; the learner asks the counter `BonusQuery` -> `BonusReply` at
sample time and publishes `Weights`, which the actors act with and the evaluator
evaluates at `Weights.eval_point`. `Start`, `Stop` and `Status` run the runs; `Metrics`
and `History` carry their rows.

shared/net/wire.py derives its schema (field names and types, checked on every decode)
from these classes, so a field added here is on the wire and checked there. A field
of a typed value (`Start.assign`, an `Assignment`) travels as the map its `to_wire`
gives and is read back through its `from_wire`, which refuses anything else.
"""

from __future__ import annotations

import dataclasses
import os
import re
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np


class WireError(ValueError):
    """A message that must be dropped: undecodable, wrong version, wrong shape."""


# A run id names folders (data_dir/learner/<run>, data_dir/counter/<run>) and a chunk of
# every per-run key (macb/run/<run>/...): letters, digits and `._-`, not starting with a
# dot or a dash, at most 128 characters, so it can neither climb out of a data dir nor
# reach into another key.
_RUN_ID = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._-]{0,127}")


def run_id_error(run: str) -> str | None:
    """Why `run` cannot be a run's id, or None: every service refuses a start naming
    such an id (services/common.py), so no path or key is ever built from one."""
    if _RUN_ID.fullmatch(run):
        return None
    return f"run id: {run[:64]!r} is not a safe name (letters, digits, '._-', at most 128)"


# The longest service id, in UTF-8 bytes: ids travel in keys and in the counter's log
# records (the actor's id, after a 2-byte length), and no deployment names one longer.
MAX_ID_BYTES = 255


def is_service_id(value: Any) -> bool:
    """A non-empty string of at most MAX_ID_BYTES bytes."""
    return isinstance(value, str) and 0 < len(value.encode()) <= MAX_ID_BYTES


def _service_ids(value: Any, name: str) -> tuple[str, ...]:
    """A non-empty list of distinct service (or run) ids, or a WireError naming `name`."""
    if not isinstance(value, list | tuple) or not value:
        raise WireError(f"assignment: field {name!r} is not a non-empty list")
    if not all(is_service_id(v) for v in value):
        raise WireError(f"assignment: field {name!r} holds something other than an id")
    if len(set(value)) != len(value):
        raise WireError(f"assignment: field {name!r} names an id twice")
    return tuple(value)


@dataclass(frozen=True)
class Assignment:
    """The services of a run or a run group, by id, as the start names them: one
    learner, its actors in rank order, the counter and the evaluator (None: none named),
    and for a run group its runs in order (run r is member r of the group's learner).

    Files, the API's store and REST show it as the map `to_wire` gives, the same map
    a `Start` carries; `from_wire` reads such a map back and refuses anything else, so
    what a service acts on is always a whole assignment.
    """

    learner: str
    actors: tuple[str, ...]
    counter: str | None = None
    evaluator: str | None = None
    group: tuple[str, ...] | None = None

    def names(self, role: str, service_id: str) -> bool:
        """Does it name `service_id` as its `role` (an actor: as one of `actors`)?"""
        if role == "actor":
            return service_id in self.actors
        return role in ("learner", "counter", "evaluator") and getattr(self, role) == service_id

    def services(self) -> list[tuple[str, str]]:
        """(role, id) of every service it names: counter, learner, evaluator, actors."""
        one = [("counter", self.counter), ("learner", self.learner), ("evaluator", self.evaluator)]
        return [(r, s) for r, s in one if s is not None] + [("actor", a) for a in self.actors]

    def held(self) -> set[str]:
        """The services the run keeps from other runs while it runs: all but the
        counter, which serves many runs."""
        return {s for r, s in self.services() if r != "counter"}

    def to_wire(self) -> dict[str, Any]:
        """The map the wire, files and the store hold (keys of None fields left out)."""
        group = None if self.group is None else list(self.group)
        out: dict[str, Any] = {"counter": self.counter, "learner": self.learner}
        out["evaluator"] = self.evaluator
        out |= {"actors": list(self.actors), "group": group}
        return {k: v for k, v in out.items() if v is not None}

    @classmethod
    def from_wire(cls, value: Any) -> Assignment:
        """The assignment a map holds; WireError naming the field and why if it holds
        anything but one (a learner, at least one actor, ids as strings, no other key)."""
        if not isinstance(value, Mapping):
            raise WireError("assignment: not a map")
        for key in value:
            if key not in _ASSIGNMENT_FIELDS:
                raise WireError(f"assignment: unknown field {key!r}")
        for name in ("learner", "actors"):
            if name not in value:
                raise WireError(f"assignment: field {name!r} is missing")
        for name in ("learner", "counter", "evaluator"):
            one = value.get(name)
            if (one is not None or name == "learner") and not is_service_id(one):
                raise WireError(f"assignment: field {name!r} is not a service id")
        group = value.get("group")
        return cls(
            learner=value["learner"],
            actors=_service_ids(value["actors"], "actors"),
            counter=value.get("counter"),
            evaluator=value.get("evaluator"),
            group=None if group is None else _service_ids(group, "group"),
        )


_ASSIGNMENT_FIELDS = frozenset(f.name for f in dataclasses.fields(Assignment))


@dataclass(frozen=True)
class Message:
    """Every message names its run."""

    TYPE: ClassVar[str] = ""
    run: str


@dataclass(frozen=True)
class Transitions(Message):
    """actor -> counter, learner: numbered training transitions."""

    TYPE: ClassVar[str] = "transitions"
    actor: str  # service id of the actor
    seq: int  # number of the first transition in the batch (0-based, per actor)
    obs: np.ndarray  # (n, joint_obs) float32
    act: np.ndarray  # (n, joint_act) float32
    rew: np.ndarray  # (n,) float32, extrinsic
    next_obs: np.ndarray  # (n, joint_obs) float32
    done: np.ndarray  # (n,) float32
    collisions: np.ndarray  # (n,) int32
    policy_version: int  # the weights' version that chose these actions

    def __len__(self) -> int:
        return len(self.rew)


@dataclass(frozen=True)
class Ack(Message):
    """counter, learner -> actors: the next sequence number expected from each actor;
    `window`: the learner's credits (how far an actor may run ahead), 0 from the counter.
    `attempt`: the attempt of the run it counts or learns (its start's): acks only move
    forward, so a reader of another attempt drops it, as a counter that restored an
    ended attempt from disk acks that attempt's positions every second (None: its start
    named none, or an older peer)."""

    TYPE: ClassVar[str] = "ack"
    service: str
    acked: dict[str, int]
    window: int
    attempt: int | None = None


@dataclass(frozen=True)
class Weights(Message):
    """learner -> actors, evaluator: the actors' weights after `updates` updates (only the
    latest matters to an actor; the evaluator evaluates every `eval_point`)."""

    TYPE: ClassVar[str] = "weights"
    version: int
    updates: int
    env_steps: int
    episodes: int
    eval_point: int  # the episode to evaluate at, or -1
    collisions_cum: int
    actors: list[dict[str, np.ndarray]]  # per agent: {parameter name: array}
    stats: dict[str, Any]  # the learner's stats at this point, for the evaluator's row
    incarnation: str  # the learner process that made them: a restart's weights are new
    # earlier evaluation points with no row yet, so the evaluator waits for them first
    unreported: list[int] = field(default_factory=list)
    # the attempt of the run they are of (its start's): an actor or evaluator serving
    # another attempt drops them, as it may hold them from before its start
    attempt: int | None = None


def same_attempt(a: int | None, b: int | None) -> bool:
    """Whether two attempts of a run may be the same one: either naming none (an older
    peer, a starter that never starts a run twice) is taken as the same."""
    return a is None or b is None or a == b


def new_incarnation(learner: str) -> str:
    """A learner's run start's `Weights.incarnation`: its id, process and start time, so
    a restart's weights, and another attempt's, are told apart from these."""
    return f"{learner}:{os.getpid()}:{time.time_ns()}"


def learner_of(incarnation: str) -> str | None:
    """The learner id a `new_incarnation` names; None for one it did not make (an older
    learner's, or empty)."""
    parts = incarnation.rsplit(":", 2)
    return parts[0] if len(parts) == 3 and parts[0] else None


@dataclass(frozen=True)
class ActRequest(Message):
    """actor -> learner (lockstep): the observations step `seq` acts on; answered once
    every earlier step is counted, in replay and learnt. (joint_obs,) for a run, (R,
    joint_obs) for a run group's R worlds."""

    TYPE: ClassVar[str] = "act_request"
    actor: str
    seq: int
    obs: np.ndarray


@dataclass(frozen=True)
class Action(Message):
    """learner -> that actor: the policy's action(s) for step `seq` (noise is the actor's).
    `ended`: the runs of its group the learner has ended by their rule, so that the actor
    retires them before it steps with these actions. The learner's "completed" status
    says so too, but on another key: a session's subscriptions are not delivered in
    order relative to each other, so the status may come after this answer."""

    TYPE: ClassVar[str] = "action"
    seq: int
    act: np.ndarray
    ended: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class BonusQuery(Message):
    """learner -> counter: the rows of a sampled minibatch to price. `attempt`: the
    attempt of the run the learner serves (its start's): a counter holding another
    attempt's tables (one restored from disk after that attempt ended) refuses it (None:
    its start named none, or an older learner)."""

    TYPE: ClassVar[str] = "bonus_query"
    obs: np.ndarray
    act: np.ndarray
    attempt: int | None = None


@dataclass(frozen=True)
class BonusReply(Message):
    """counter -> learner: each row's count and bonus, from the counts at that moment,
    and the counter's table stats then (what the learner's next point reports).
    `service`: the counter that answered: every counter answers the run's key, and the
    learner takes only its run's counter's reply (None: an older counter)."""

    TYPE: ClassVar[str] = "bonus_reply"
    counts: np.ndarray
    bonus: np.ndarray
    tables: dict[str, Any] = field(default_factory=dict)
    service: str | None = None


@dataclass(frozen=True)
class Metrics(Message):
    """any service -> watchers: a metric point or stats. `attempt`: the attempt of the
    run it came from (its start's), so that the API and the learner of a retried run's
    next attempt drop the rows an ended attempt's evaluator still sends (None: its start
    named none, or an older peer)."""

    TYPE: ClassVar[str] = "metrics"
    source: str
    data: dict[str, Any]
    attempt: int | None = None


@dataclass(frozen=True)
class History(Message):
    """evaluator -> the API (a reply to a history get): every row of the run so far, of
    the run's `attempt` that evaluator served (an ended attempt's evaluator may answer
    too)."""

    TYPE: ClassVar[str] = "history"
    source: str
    rows: list[dict[str, Any]]
    state: str
    attempt: int | None = None


@dataclass(frozen=True)
class Start(Message):
    """control -> services: start (or join) a run; `assign` names the services that
    serve it (on the wire: its `to_wire` map). `attempt`: which attempt of the run this
    is (the API's `attempts`: 2 once retried), stamped on the services' statuses in it;
    None from a starter that never starts a run twice."""

    TYPE: ClassVar[str] = "start"
    config: dict[str, Any]
    assign: Assignment
    attempt: int | None = None


@dataclass(frozen=True)
class Stop(Message):
    """control -> services: stop a run."""

    TYPE: ClassVar[str] = "stop"
    reason: str


def _field(value: Mapping[str, Any], name: str, kind: type | tuple[type, ...], where: str) -> Any:
    """`value[name]` if it is a `kind` (never a bool for an int), else a WireError."""
    one = value.get(name)
    if not isinstance(one, kind) or (isinstance(one, bool) and kind is not bool):
        raise WireError(f"{where}: field {name!r} is not {getattr(kind, '__name__', kind)}")
    return one


@dataclass(frozen=True)
class Resumed:
    """What a learner's resume restored for a run: the cut it went on from
    (`from_episode`, None: its log alone), its learner's updates, the replay's rows and
    the held batches then, how long it took, and a group's runs. Its "running" status,
    its "completed" one and its info reply say it (the API notes the restart from it)."""

    run: str
    from_episode: int | None
    updates: int
    replay_rows: int
    held_batches: int
    seconds: float
    group: tuple[str, ...] | None = None

    def to_wire(self) -> dict[str, Any]:
        """The map the wire, the info reply and the log hold (no `group` for a run alone)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return out | {"group": list(self.group)} if self.group is not None else out

    def grouped(self, runs: list[str]) -> Resumed:
        return dataclasses.replace(self, group=tuple(runs))

    @classmethod
    def from_wire(cls, value: Any) -> Resumed:
        """The resume a map says; WireError naming the field for anything else."""
        if not isinstance(value, Mapping):
            raise WireError("resumed: not a map")
        cut = value.get("from_episode")
        if cut is not None:
            cut = _field(value, "from_episode", int, "resumed")
        group = value.get("group")
        return cls(
            run=_field(value, "run", str, "resumed"),
            from_episode=cut,
            updates=_field(value, "updates", int, "resumed"),
            replay_rows=_field(value, "replay_rows", int, "resumed"),
            held_batches=_field(value, "held_batches", int, "resumed"),
            seconds=float(_field(value, "seconds", (int, float), "resumed")),
            group=None if group is None else _service_ids(group, "group"),
        )


@dataclass(frozen=True)
class Status(Message):
    """a service -> watchers: its state in a run (running, completed, failed, ...).

    What a reader acts on is a field of its own: why it failed or stopped (`reason`),
    an actor's transitions published in all (`final_seq`, when completed: the learner
    waits for that many), the evaluator's points (`points`, when completed: the run
    completes once that many rows are stored), a restarted learner's resume
    (`resumed`). `detail` holds the rest, shown and stored but read by no rule: where
    the service is (rank, episodes, its runs) and its stats. An older peer sent all of
    it in `detail`: shared/net/wire.py reads those keys into the fields. `attempt`: the
    attempt of the run it came from (its start's), so that a reader of a later attempt
    drops it: a service may answer the stop of an ended attempt after the run's next
    attempt started (None: its start named none).
    """

    TYPE: ClassVar[str] = "status"
    service: str
    state: str
    detail: dict[str, Any]
    reason: str | None = None
    final_seq: int | None = None
    points: int | None = None
    resumed: Resumed | None = None
    attempt: int | None = None

    def fields(self) -> dict[str, Any]:
        """The status as one flat map, as watchers show and store it: `detail` and each
        field that is set (`resumed` as its map)."""
        typed: dict[str, Any] = {
            "reason": self.reason,
            "final_seq": self.final_seq,
            "points": self.points,
        }
        typed["resumed"] = None if self.resumed is None else self.resumed.to_wire()
        return self.detail | {k: v for k, v in typed.items() if v is not None}


MESSAGES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        Transitions,
        Ack,
        Weights,
        ActRequest,
        Action,
        BonusQuery,
        BonusReply,
        Metrics,
        History,
        Start,
        Stop,
        Status,
    )
}
