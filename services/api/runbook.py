"""The runs the API's scheduler follows, and what their events write into the store.

No bus: the scheduler subscribes and hands over what arrives (metrics, statuses,
liveliness) in batches; the book decodes it, feeds each run's `Watch`, and writes
evaluation rows, the services' states, the latest stats, the run's reason and its
final status. So a run keeps its history whether or not anyone watches it over HTTP,
and what the scheduler does on the bus (start, stop, ask the evaluator's history)
stays in the scheduler. What a retried run's ended attempt still sends is dropped.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any, TypeVar

from shared.net import bus as keys
from shared.net.messages import Assignment, Metrics, Status, same_attempt
from shared.net.monitor import Graces, live_peer
from shared.net.wire import WireError, decode

from .store import Store
from .watch import Ending, Watch

M = TypeVar("M", Metrics, Status)

log = logging.getLogger("macb.api.scheduler")

ENDED_WATCH_S = 3.0  # an ended run's late rows are still stored this long


class RunBook:
    """Every watched run by id, the liveliness tokens seen, and the store they write."""

    def __init__(
        self,
        store: Store,
        graces: Graces,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.store = store
        self.graces = graces
        self.clock = clock
        self.listeners: list[Callable[[], None]] = []  # called after the store changed
        self.watches: dict[str, Watch] = {}
        self.alive: set[tuple[str, str]] = set()  # (role, id) with a liveliness token

    def watch(self, run: dict[str, Any], started: float) -> Watch:
        """Follow a store row (a run just claimed, or running when the API started)."""
        stats = self.store.point_stats([run["id"]])[run["id"]]
        w = Watch.of(run, started, self.graces, stats)
        self.watches[w.run] = w
        return w

    def to_follow(self, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
        """The running rows no watch follows yet, to re-attach to. A row whose stored
        assignment is refused (this API writes none such) fails saying so, its services
        told to stop: no watch could ever end it."""
        out = []
        for run in rows:
            if run["id"] in self.watches or not run.get("assign"):
                continue
            try:
                Assignment.from_wire(run["assign"])
            except WireError as err:
                log.error("run %s cannot be followed: %s", run["id"], err)
                reason = f"its stored assignment is refused: {err}"
                self.store.finish(run["id"], "failed", reason, stop_sent=False)
                continue
            out.append(run)
        return out

    def drop(self, w: Watch) -> None:
        self.watches.pop(w.run, None)

    def changed(self) -> None:
        for fn in self.listeners:
            with contextlib.suppress(Exception):
                fn()

    def stopped(self, run: str, now: float) -> None:
        """A stop went out for `run` (over HTTP, or its end): its services are free."""
        w = self.watches.get(run)
        if w is not None and w.ended is None:
            w.ended = now

    def reserved(self) -> set[str]:
        """Services of runs we started that are not over yet."""
        return {sid for w in self.watches.values() if w.ended is None for sid in w.holds()}

    def superseded(self, w: Watch) -> bool:
        """The watch's run ended and was queued again since (a retry): the statuses its
        ended attempt still sends belong to no attempt the store keeps. A look-up only
        for ended watches, which live ENDED_WATCH_S. (Rows are checked by the store
        itself: `store_points`.)"""
        if w.ended is None:
            return False
        row = self.store.run(w.run)
        return row is None or row["status"] == "queued"

    # ------------------------------------------------------------ events
    def handle(self, batch: list[tuple[str, str, Any]]) -> bool:
        """A batch of (kind, key, payload) events; True if a liveliness token came up
        (services may be free for a queued run)."""
        rows: dict[str, list[dict[str, Any]]] = {}
        came_up = False
        for kind, key, payload in batch:
            try:
                if kind == "metrics":
                    self._metrics(key, payload, rows)
                elif kind == "status":
                    self._status(key, payload)
                elif kind == "live":
                    came_up = self._live(key, payload) or came_up
            except Exception:  # one odd message must not stop the bookkeeping
                log.exception("dropped a %s event on %s", kind, key)
        for run, new in rows.items():
            self.store_points(run, new)
        if rows:
            self.changed()
        return came_up

    def store_points(self, run: str, rows: list[dict[str, Any]]) -> int:
        """Store evaluation rows of the watched attempt (the store ignores episodes it
        has); count the new ones on the run's watch. Returns how many were new.

        The store keeps them only if the watch's attempt is still the run's current
        one, checked in the insert's transaction: a stop over HTTP and a retry can both
        land before the watch learns of the stop, and a late row of the ended attempt
        would then take its episode from the new attempt's row."""
        w = self.watches.get(run)
        added = self.store.add_points(run, rows, w.attempt if w is not None else None)
        if w is not None:
            w.stored(rows, added)
        if added:
            self.changed()
        return added

    def _followed(self, key: str, payload: bytes, cls: type[M]) -> tuple[Watch, M] | None:
        """A message for a run followed here, on that run's key; None otherwise (another
        run's, or one that does not decode: the services count those)."""
        run = keys.run_of(key)
        w = self.watches.get(run or "")
        if w is None:
            return None
        try:
            msg = decode(payload, cls)
        except WireError:
            return None
        return (w, msg) if msg.run == run else None

    def _metrics(self, key: str, payload: bytes, rows: dict[str, list]) -> None:
        if (got := self._followed(key, payload, Metrics)) is not None:
            w, msg = got
            if not same_attempt(msg.attempt, w.attempt):
                return  # an ended attempt's evaluator, late: its rows are not this attempt's
            if (row := w.metrics(msg)) is not None:
                rows.setdefault(msg.run, []).append(row)

    def _status(self, key: str, payload: bytes) -> None:
        got = self._followed(key, payload, Status)
        if got is None or self.superseded(got[0]):
            return
        w, msg = got
        if not same_attempt(msg.attempt, w.attempt):
            return  # an ended attempt's (a service answered its stop after the retry began)
        note = w.status(msg, self.clock())
        if note is not None:
            log.info("run %s: %s", w.run, note)
            self.store.set_reason(w.run, "; ".join(w.notes), w.attempt)
        self.store.set_services(w.run, w.states, w.attempt)
        self.changed()

    def _live(self, key: str, up: bool) -> bool:
        if (peer := live_peer(key)) is None:
            return False
        role, sid = peer
        if up:
            self.alive.add((role, sid))
        else:
            self.alive.discard((role, sid))
        now = self.clock()
        for w in list(self.watches.values()):
            if w.ended is not None:
                continue
            before = w.monitor.waiting()
            w.monitor.peer(role, sid, up, now)
            self.show_waiting(w, before)
        return up

    def show_waiting(self, w: Watch, before: str | None) -> None:
        """The run's reason says what it waits for (a service to come back), else its notes."""
        waiting = w.monitor.waiting()
        if waiting != before:
            if before is not None and waiting is None:
                log.info("run %s: back (%s no longer)", w.run, before)
            self.store.set_reason(w.run, w.reason(), w.attempt)
            self.changed()

    # ------------------------------------------------------------ decisions
    def save_live(self, w: Watch, now: float) -> None:
        self.store.set_live(w.run, w.live, w.attempt)
        w.live_saved(now)
        self.changed()

    def decide(self, w: Watch, now: float, fill_gaps: Callable[[Watch], int]) -> Ending | None:
        """The run's ending by its monitor, if it has one now; `fill_gaps` asks the
        evaluator's history for missing points (once) before the monitor decides again."""
        row = self.store.run(w.run)
        if row is None or row["status"] != "running":
            w.ended = w.ended or now  # stopped over HTTP
            return None
        before = w.monitor.waiting()
        decision = w.monitor.decide(now)
        if decision.ask_history:
            fill_gaps(w)
            decision = w.monitor.decide(now)
        if (ending := Ending.of(decision)) is not None:
            return ending
        self.show_waiting(w, before)
        return None

    def end(self, w: Watch, ending: Ending) -> None:
        """Record a final status (the scheduler sends the stops `ending.stop` asks for)."""
        if w.live_dirty:
            self.save_live(w, self.clock())
        reason = ending.reason
        if reason is None and w.notes:
            reason = "; ".join(w.notes)
        if self.store.finish(w.run, ending.status, reason, stop_sent=not ending.stop):
            log.info("run %s %s%s", w.run, ending.status, f": {reason}" if reason else "")
        w.ended = self.clock()
        self.changed()
