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

from shared.net.monitor import live_peer

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


def reconcile_run(
    w: Watch,
    infos: Mapping[str, dict[str, Any]],
    alive: Container[tuple[str, str]],
    now: float,
    settle_s: float,
    wait_s: float,
) -> Ending | None:
    """How a running run ends that its services no longer serve (None: it goes on):
    the monitor's rule (`RunMonitor.unserved`), which `macb start` applies too."""
    decision = w.monitor.unserved(w.run, infos, alive, now, settle_s, wait_s)
    return None if decision is None else Ending.of(decision)


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
        if (peer := live_peer(key)) is None:
            continue
        role, sid = peer
        info = by_key.get((role, sid))
        out.append(
            {
                "id": sid,
                "role": role,
                "run": info.get("run") if info else None,
                "runs": list(info.get("runs") or []) if info else [],
                "rejects_total": int(info.get("rejects_total", 0)) if info else 0,
                "restarts": int(info.get("restarts", 0)) if info else 0,
                "node": info.get("node") if info and isinstance(info.get("node"), str) else None,
                "answers": info is not None,
            }
        )
    return out
