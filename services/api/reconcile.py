"""What the store says against what the bus shows, decided without the bus.

The scheduler sees a run end by its services' reports. When it was not listening (the
API restarted) or a service restarted meanwhile, the two can disagree: a run the store
calls running that no service serves any more, a service that rejoined a run the store
has ended. These functions take the services' infos (`shared.net.control.discover`),
the liveliness tokens seen, and store look-ups, and say what to do; the scheduler
does it. `worker_rows` is the same infos shaped for GET /workers.
"""

from __future__ import annotations

from collections.abc import Callable, Container, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from .watch import Ending, Watch

FINAL = ("completed", "failed", "stopped")


@dataclass(frozen=True)
class Stale:
    """A service serving a run the store has ended (it rejoined it after a restart)."""

    role: str
    service: str
    run: str
    status: str  # the run's, in the store

    @property
    def reason(self) -> str:
        """The stop message's reason."""
        return f"the run had {self.status} while this service was down"

    def __str__(self) -> str:
        return f"{self.role} {self.service} serves run {self.run}, which has {self.status}"


def serving(run: str, services: Iterable[tuple[str, str]], infos: Mapping[str, Any]) -> list[str]:
    """The run's services whose info says they serve it. Not the counter: it serves many
    runs and resumes those it had from disk when it restarts, including one whose
    learner is gone for good."""
    return [
        sid
        for role, sid in services
        if role != "counter"
        and sid in infos
        and (infos[sid].get("run") == run or run in (infos[sid].get("runs") or []))
    ]


def reconcile_run(
    w: Watch,
    infos: Mapping[str, dict[str, Any]],
    alive: Container[tuple[str, str]],
    now: float,
    settle_s: float,
    wait_s: float,
) -> Ending | None:
    """How a running run ends that its services no longer serve (None: it goes on).

    A run younger than `settle_s` is left to its start. A learner with neither a token
    nor an info is lost as if its token went away (the monitor's grace applies). A run
    no service serves for `wait_s` ended unseen: completed if its last point is in."""
    if now - w.monitor.started < settle_s:
        return None
    served = bool(serving(w.run, w.services(), infos))
    learner = w.assign.learner
    if ("learner", learner) not in alive and learner not in infos:
        w.monitor.peer("learner", learner, False, now)  # gone unseen: the same grace
    if not w.unserved_for(served, now, wait_s):
        return None
    return w.unobserved_end()


def stale_runs(
    infos: Mapping[str, dict[str, Any]],
    watched: Container[str],
    run_row: Callable[[str], dict[str, Any] | None],
) -> list[Stale]:
    """Every service that rejoined (after a restart) a run the store (`run_row`) says
    has ended: it is to be told to stop it, so it is free again. Watched runs are left
    to the watch, the counter to its own files."""
    out = []
    for info in infos.values():
        run = info.get("run")
        if info.get("role") == "counter" or not run or run in watched:
            continue
        row = run_row(run)
        if row is not None and row["status"] in FINAL:
            out.append(Stale(info["role"], info["id"], run, row["status"]))
    return out


def worker_rows(tokens: Iterable[str], infos: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """GET /workers: one row per liveliness token (`macb/live/{role}/{id}`), with what
    its service's info says (`answers`: whether it answered at all)."""
    by_key = {(i["role"], i["id"]): i for i in infos}
    out = []
    for key in sorted(set(tokens)):
        parts = key.split("/")
        if len(parts) != 4:
            continue
        role, sid = parts[2], parts[3]
        info = by_key.get((role, sid))
        out.append(
            {
                "id": sid,
                "role": role,
                "run": info.get("run") if info else None,
                "runs": list(info.get("runs") or []) if info else [],
                "rejects_total": int(info.get("rejects_total", 0)) if info else 0,
                "restarts": int(info.get("restarts", 0)) if info else 0,
                "answers": info is not None,
            }
        )
    return out
