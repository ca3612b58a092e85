"""A service's reply to an info query (`macb/info/{role}/{id}`), as typed values.

Every service answers with its id and role, the run(s) it serves, its malformed-message
counts, its restarts and what its last start resumed; the counter adds each run's
stats (under `runs`, where the others list their runs), whether it is ready and its
snapshot interval; the API its HTTP address. `node` is the machine it runs on, by which
the scheduler keeps a run's services together. The reply is JSON: `to_json` gives the
map it always was (same keys, same order), `from_json` reads one for a reader (None
for a reply that is not a service's info: it is skipped, as it always was).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class ServiceInfo:
    """What every service says about itself. `resumed`: a learner's `Resumed` map, or
    where a restarted actor went on from (None: its start resumed nothing)."""

    id: str
    role: str
    run: str | None = None
    runs: list[str] = field(default_factory=list)
    rejects: dict[str, int] = field(default_factory=dict)
    rejects_total: int = 0
    restarts: int = 0
    resumed: dict[str, Any] | None = None
    node: str | None = None  # the node it runs on (shared.settings.node_name)

    def to_json(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(ServiceInfo)}

    @classmethod
    def from_json(cls, value: Any) -> ServiceInfo | None:
        """The info a reply holds, or None unless it names a service (a string id and
        role); other keys are taken as they came."""
        if not isinstance(value, dict):
            return None
        if not (isinstance(value.get("id"), str) and isinstance(value.get("role"), str)):
            return None
        runs, rejects, resumed = value.get("runs"), value.get("rejects"), value.get("resumed")
        total, restarts = value.get("rejects_total"), value.get("restarts")
        return ServiceInfo(
            id=value["id"],
            role=value["role"],
            run=value.get("run") if isinstance(value.get("run"), str) else None,
            runs=list(runs) if isinstance(runs, list | dict) else [],
            rejects=dict(rejects) if isinstance(rejects, dict) else {},
            rejects_total=total if isinstance(total, int) else 0,
            restarts=restarts if isinstance(restarts, int) else 0,
            resumed=resumed if isinstance(resumed, dict) else None,
            node=node if isinstance(node := value.get("node"), str) else None,
        )


@dataclass(frozen=True)
class CounterInfo(ServiceInfo):
    """A counter's: each run's stats (`CounterStats`' map and the actors it acked, under
    `runs`), whether its tables are loaded, its snapshot interval."""

    run_stats: dict[str, dict[str, Any]] = field(default_factory=dict)
    ready: bool = False
    snapshot_s: float = 0.0

    def to_json(self) -> dict[str, Any]:
        out = super().to_json()
        out["runs"] = self.run_stats  # (in place of the list: the runs are its keys)
        return out | {"ready": self.ready, "snapshot_s": self.snapshot_s}

    @classmethod
    def from_json(cls, value: Any) -> CounterInfo | None:
        base = ServiceInfo.from_json(value)
        if base is None:
            return None
        runs = value.get("runs")
        stats = (
            {r: s for r, s in runs.items() if isinstance(s, dict)} if isinstance(runs, dict) else {}
        )
        return CounterInfo(
            **{f.name: getattr(base, f.name) for f in dataclasses.fields(ServiceInfo)},
            run_stats=stats,
            ready=value.get("ready") is True,
            snapshot_s=snapshot
            if isinstance(snapshot := value.get("snapshot_s"), int | float)
            else 0.0,
        )


@dataclass(frozen=True)
class ApiInfo(ServiceInfo):
    """The API's: it serves no run itself (nothing to resume); where its HTTP listens."""

    http: str | None = None

    def to_json(self) -> dict[str, Any]:
        out = {k: v for k, v in super().to_json().items() if k != "resumed"}
        return out | {"http": self.http}
