"""The stats the services publish, one frozen dataclass each, like the messages.

A learner, a counter and an actor publish their stats as a `Metrics` message's map
(the API keeps each source's latest as the run's `live` row, the dashboard shows it),
and the learner's ride in its `Weights` for the evaluator's row. On the wire they stay
the maps they were (`to_wire` gives the same keys in the same order), so an older
peer's are read as well; `from_wire` reads such a map for a reader, a key it lacks (an
older or a counter-less peer's) as 0, every value as it came (a row made from it is the
row made before these types).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

S = TypeVar("S", bound="_Stats")

SPENT_PREFIX = "ms_per_update_"  # a learner's time per update in each phase


@dataclass(frozen=True)
class _Stats:
    """`to_wire`/`from_wire` over a dataclass's own fields (in their order)."""

    def to_wire(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    @classmethod
    def from_wire(cls: type[S], data: Mapping[str, Any]) -> S:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})


@dataclass(frozen=True)
class CounterStats(_Stats):
    """A counter's stats for a run: its tables, what it counted and refused, its
    query latency and its persistence. The table fields alone (size, count-1 %,
    counted) also come in a bonus reply, for the learner's next evaluation point."""

    table_size: int = 0
    count1_pct: float = 0.0
    counted_transitions: int = 0
    duplicates: int = 0
    gaps: int = 0
    rejects_total: int = 0
    run_rejects: int = 0
    memory_bytes: int = 0
    transitions_per_sec: float = 0.0
    query_p50_ms: float = 0.0
    query_p99_ms: float = 0.0
    queries: int = 0
    uncounted_rows_queried: int = 0
    wal_records: int = 0
    snapshots: int = 0
    actors: int = 0


@dataclass(frozen=True)
class ActorStats(_Stats):
    """An actor's stats for a run: where it is among the run's actors, what it
    published and resent, its speed, and in lockstep its wait for each action.
    `group`: a run group's size (None for a run alone: no key on the wire)."""

    rank: int = 0
    episodes: int = 0
    published: int = 0
    policy_version: int = 0
    resends: int = 0
    steps_per_sec: float = 0.0
    rejects_total: int = 0
    act_wait_ms: float = 0.0
    group: int | None = None

    def to_wire(self) -> dict[str, Any]:
        out = super().to_wire()
        return out if self.group is not None else {k: v for k, v in out.items() if k != "group"}


@dataclass(frozen=True)
class LearnerStats:
    """A learner's stats for a run: progress, replay ratio and lag, the bonus queries,
    the cuts; `spent`, its time per update in each phase (on the wire as
    `ms_per_update_<phase>` keys), and `own`, its algorithm's stats (the learner's
    `stats()`, which take precedence over any key above). In a `Weights` at an
    evaluation point also the counter's stats then and what the bonus did since the
    last point (`bonus_mean`, `bonus_std`, `sampled_count1_pct`)."""

    updates: int = 0
    ingested: int = 0
    episodes_ingested: int = 0
    replay_ratio: float = 0.0
    policy_lag: float = 0.0
    policy_version: int = 0
    wall_s: float = 0.0
    steps_per_sec: float = 0.0
    updates_per_sec: float = 0.0
    backlog: int = 0
    window_open: bool = False
    bonus_p50_ms: float = 0.0
    bonus_p99_ms: float = 0.0
    bonus_wait_ms_per_update: float = 0.0
    bonus_queries: int = 0
    bonus_rows_per_query: float = 0.0
    bonus_failures: int = 0  # answered by no usable reply (malformed, wrong shape)
    bonus_unanswered: int = 0  # no reply in time: its minibatches priced again later
    bonus_refused: int = 0  # refused by the counter, saying why: priced again later too
    bonus_mean: float = 0.0
    rejects_total: int = 0
    contended_updates: int = 0
    eval_rows_seen: int = 0
    cuts: int = 0
    cut_ms_mean: float = 0.0
    cut_bytes: int = 0
    spent: dict[str, float] = field(default_factory=dict)  # phase -> ms per update
    own: dict[str, float] = field(default_factory=dict)
    # A Weights' (empty maps between evaluation points): the counter's stats as it
    # gave them (a bonus reply's tables or its info's run stats), the bonus's since the
    # last point.
    counter: dict[str, Any] | None = None
    bonus: dict[str, float] | None = None

    def to_wire(self) -> dict[str, Any]:
        """The map published: the fields, the phases, the algorithm's own; then, in a
        Weights, `counter` and `bonus`."""
        skip = ("spent", "own", "counter", "bonus")
        out = {
            f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in skip
        }
        out |= {SPENT_PREFIX + k: v for k, v in self.spent.items()}
        out |= self.own
        if self.counter is None and self.bonus is None:
            return out
        return out | {"counter": dict(self.counter or {}), "bonus": dict(self.bonus or {})}

    @property
    def tables(self) -> CounterStats:
        """The counter's stats a Weights carries (all 0 when it carries none)."""
        return CounterStats.from_wire(self.counter or {})

    def bonus_stat(self, name: str) -> float:
        """One of what the bonus did since the last point (0.0 when not carried)."""
        return (self.bonus or {}).get(name, 0.0)

    @classmethod
    def from_wire(cls, data: Mapping[str, Any]) -> LearnerStats:
        names = {f.name for f in dataclasses.fields(cls)} - {"spent", "own", "counter", "bonus"}
        fields = {k: v for k, v in data.items() if k in names}
        spent = {
            k.removeprefix(SPENT_PREFIX): v for k, v in data.items() if k.startswith(SPENT_PREFIX)
        }
        skip = names | {"counter", "bonus"}
        own = {k: v for k, v in data.items() if k not in skip and not k.startswith(SPENT_PREFIX)}
        counter, bonus = data.get("counter"), data.get("bonus")
        return cls(
            **fields,
            spent=spent,
            own=own,
            counter=dict(counter) if isinstance(counter, Mapping) else None,
            bonus=dict(bonus) if isinstance(bonus, Mapping) else None,
        )


def _number(value: Any) -> bool:
    return isinstance(value, int | float)  # (a bool too: `window_open`)


def learner_stats_error(data: Mapping[str, Any]) -> str | None:
    """Why a `Weights` message's `stats` cannot be read into a point's row, or None:
    every value a number but `counter` and `bonus`, maps (or nil) with string names
    whose values a row reads (the bonus's, `CounterStats`' own) are numbers. (`decode`
    has checked the names are strings: `LearnerStats.from_wire` raised on another.)"""
    counter_fields = {f.name for f in dataclasses.fields(CounterStats)}
    for name, value in data.items():
        if name in ("counter", "bonus"):
            if value is None:
                continue
            if not isinstance(value, Mapping) or not all(isinstance(k, str) for k in value):
                return f"{name} is not a map of names"
            read = value if name == "bonus" else {k: value[k] for k in counter_fields & set(value)}
            if not all(_number(v) for v in read.values()):
                return f"{name} holds a value that is not a number"
        elif not _number(value):
            return f"{name!r:.60} is not a number"
    return None
