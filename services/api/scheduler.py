"""The API's scheduler: one thread with its own bus session.

- Assigns queued runs, oldest first, to free services (`shared.net.control`), and starts
  them. With `group_size` > 1, queued runs of one experiment that can share a group
  (lockstep, one actor, same task and networks: `shared.groups.group_error`)
  start together on one learner, actor and evaluator, up to `group_size` runs: a run
  group, each run keeping its own id, rows and status. Services it has started runs on
  stay reserved until those runs end, so two runs never land on one learner while the
  services' own info catches up.
- Subscribes to each running run's metrics and status keys; Zenoh's callbacks only
  enqueue, and this thread writes every evaluation row, the services' states and
  the latest stats into the store as they arrive. So a run keeps its history
  whether or not anyone watches it over HTTP.
- Decides each run's status: failed as soon as a service reports it (with its
  reason), or when the liveliness token of its learner, evaluator or an actor goes
  away and does not come back within `peer_grace_s` (MACB_PEER_GRACE_S, 30 s: a
  restarted service rejoins its run, a restarted router brings every token back);
  stopped when someone stops it; completed when the learner and the evaluator have
  completed and every evaluation row is in. A dead counter is given
  `counter_grace_s` (it restarts from its snapshot and log). A learner that resumed
  from a cut says so in its status, and the run's record keeps it as its note.
- A service that rejoins a run after a restart while that run had ended meanwhile is
  told to stop it, so it is free again. A service that missed a run's start (it died
  just after the run was assigned to it) is sent the start again once seen, on two
  looks, not serving the run while others do (`shared.net.monitor.start_lost`): else
  they wait on it for good.
- Sends the stop messages the HTTP side asks for (a failed run's other services are
  stopped too, so they are free for the next run).
- On start (after an API restart), re-attaches to the runs the store says are
  running and asks each run's evaluator for the rows it published meanwhile
  (`macb/run/{run}/history/eval`), so no point is lost while the API is down; a run
  whose services no longer serve it ended while nobody listened, and is resolved
  from what was stored. At a run's end, rows still missing are asked for once more.
- A run queued again (POST /experiments/{id}/retry) starts afresh: what the attempt
  that ended still sends (late rows, statuses) is not stored on the queued run.

This class is the shell: the bus session and its reconnects, the subscriptions, the
timers, and the calls to its parts, which have no bus: `planner.py` (the queue pass:
what starts, on which services, in which groups), `runbook.py` (the watched runs and
what their events write into the store), `watch.py` (one run's state and monitor),
`reconcile.py` (the store against what the bus shows).
"""

from __future__ import annotations

import contextlib
import json
import logging
import queue
import threading
import time
from typing import Any

from services.common import restarts
from shared.config import ConfigError, make_config
from shared.net import bus as keys
from shared.net.bus import Bus
from shared.net.control import discover, history_rows, send_start, send_stop
from shared.net.info import ApiInfo
from shared.net.monitor import Graces, live_peer, start_lost
from shared.net.monitor import peer_grace_s as peer_grace
from shared.settings import node_name

from .planner import Invalid, QueuePass
from .reconcile import reconcile_run, stale_runs, worker_rows
from .runbook import ENDED_WATCH_S, RunBook
from .store import Store
from .watch import Ending, Watch, flat_row

log = logging.getLogger("macb.api.scheduler")

ASSIGN_RETRY_S = 1.0  # the queue is tried this often when nothing woke it


class Scheduler:
    """The API's bus side: one thread that starts queued runs and follows running ones."""

    def __init__(
        self,
        store: Store,
        connect: list[str],
        service_id: str = "api",
        http_url: str = "",
        tick_s: float = 0.2,
        counter_grace_s: float = 120.0,
        start_timeout_s: float = 60.0,
        completion_grace_s: float = 5.0,
        reconcile_s: float = 3.0,
        history_timeout_s: float = 2.0,
        peer_grace_s: float | None = None,
        group_size: int = 1,
    ) -> None:
        self.store = store
        self.group_size = group_size
        self.connect = connect
        self.service_id = service_id
        self.http_url = http_url
        self.tick_s = tick_s
        self.reconcile_s = reconcile_s
        self.history_timeout_s = history_timeout_s
        self.graces = Graces(
            peer_s=peer_grace() if peer_grace_s is None else peer_grace_s,
            counter_s=counter_grace_s,
            completion_s=completion_grace_s,
            start_s=start_timeout_s,
        )
        self.book = RunBook(store, self.graces)
        self.listeners = self.book.listeners  # called after the store changed
        self.events: queue.Queue[tuple[str, str, Any]] = queue.Queue()
        self.bus: Bus | None = None
        self.connected = threading.Event()
        self._subs: dict[str, list[Any]] = {}  # run -> its subscriptions
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._main, name="macb-api-scheduler", daemon=True)
        self._last_reconcile = 0.0
        self._last_assign_try = 0.0
        # Liveliness tokens as the subscription last said, and each service's last info:
        # GET /workers reads these, so a query that times out on a loaded machine does
        # not make the cluster look empty for a moment.
        self._tokens: set[str] = set()
        self._infos: dict[tuple[str, str], dict[str, Any]] = {}
        self._lock = threading.Lock()

    # ------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self._thread.start()

    def close(self, timeout: float = 10.0) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout)

    def wake(self) -> None:
        """Something changed on the HTTP side (a new experiment, a stop): act now."""
        self._wake.set()
        self.events.put(("wake", "", None))

    def _main(self) -> None:
        delay = 0.2
        while not self._stop.is_set():
            try:
                self.bus = Bus(self.connect)
            except Exception as err:  # the router is not up (yet)
                log.warning("cannot reach the bus at %s: %s (retrying)", self.connect, err)
                self._stop.wait(delay)
                delay = min(5.0, delay * 2)
                continue
            try:
                self._serve()
            except Exception:
                log.exception("scheduler failed; reconnecting")
            finally:
                self.connected.clear()
                self._subs.clear()
                with self._lock:
                    self._tokens.clear()
                    self._infos.clear()
                self.book.watches.clear()
                with contextlib.suppress(Exception):
                    self.bus.close()
                self.bus = None

    def _serve(self) -> None:
        bus = self.bus
        assert bus is not None
        bus.token(keys.k_live("api", self.service_id))
        bus.queryable(keys.k_info("api", self.service_id), self._info_reply)
        bus.watch_liveliness(keys.k_live("*", "*"), self._on_live)
        self.connected.set()
        log.info("scheduler connected to %s", self.connect)
        self._reattach()
        while not self._stop.is_set():
            self._drain(timeout=self.tick_s)
            self._send_stops()
            self._assign_queued()
            self._check_runs()

    def _on_live(self, key: str, up: bool) -> None:
        with self._lock:
            if up:
                self._tokens.add(key)
            else:
                self._tokens.discard(key)
        self.events.put(("live", key, up))

    def _info_reply(self, key: str, payload: bytes) -> bytes:
        info = ApiInfo(
            id=self.service_id,
            role="api",
            restarts=restarts(),
            node=node_name(),
            http=self.http_url,
        )
        return json.dumps(info.to_json()).encode()

    # ------------------------------------------------------------ events
    def _drain(self, timeout: float) -> None:
        """Hand every queued bus event to the book; wait up to `timeout` for the first."""
        try:
            first = self.events.get(timeout=timeout)
        except queue.Empty:
            return
        batch = [first]
        with contextlib.suppress(queue.Empty):
            while len(batch) < 10_000:
                batch.append(self.events.get_nowait())
        if self.book.handle(batch):
            self._wake.set()

    def _watch(self, run: dict[str, Any], started: float) -> Watch:
        bus = self.bus
        assert bus is not None
        old = self.book.watches.get(run["id"])
        if old is not None:  # the ended attempt of a run queued again
            self._unwatch(old)
        w = self.book.watch(run, started)
        put = self.events.put
        self._subs[w.run] = [
            bus.subscribe(keys.k_metrics(w.run, "**"), lambda k, p: put(("metrics", k, p))),
            bus.subscribe(keys.k_status(w.run, "*"), lambda k, p: put(("status", k, p))),
        ]
        return w

    def _unwatch(self, w: Watch) -> None:
        for h in self._subs.pop(w.run, []):
            if self.bus is not None:
                self.bus.undeclare(h)
        self.book.drop(w)

    def _end(self, w: Watch, ending: Ending) -> None:
        """Record a final status; tell the run's services to stop if it asks so."""
        self.book.end(w, ending)
        if ending.stop:
            self._send_stops()
        self._wake.set()  # its services are free for a queued run

    def _send_stops(self) -> None:
        if self.bus is None:
            return
        for run, reason in self.store.stops_to_send():
            send_stop(self.bus, run, reason)
            self.store.stop_sent(run)
            self.book.stopped(run, time.monotonic())

    # ------------------------------------------------------------ the queue
    def _assign_queued(self) -> None:
        now = time.monotonic()
        if now - self._last_assign_try < ASSIGN_RETRY_S and not self._wake.is_set():
            return
        self._wake.clear()
        queued = self.store.runs_with_status("queued")
        if not queued:
            return
        self._last_assign_try = now
        assert self.bus is not None
        plan = QueuePass(
            queued, discover(self.bus, timeout=1.0), self.book.reserved(), self.group_size
        )
        for start in plan.proposals():
            if isinstance(start, Invalid):
                self.store.finish(start.run, "failed", start.reason)
                continue
            if not self.store.claim_all(start.ids, start.assign):
                continue  # stopped meanwhile
            for row in start.attempt_rows():
                self._watch(row, time.monotonic())
            for member, member_config in start.members:
                send_start(
                    self.bus, member["id"], member_config, start.assign, member.get("attempts")
                )
            plan.took(start)
            a = start.assign
            log.info("run %s started on %s", start.ids if a.group else start.ids[0], a.to_wire())
            self.book.changed()
        self.store.set_waiting(plan.waiting)

    # ------------------------------------------------------------ run status
    def _check_runs(self) -> None:
        now = time.monotonic()
        for w in list(self.book.watches.values()):
            if self.book.superseded(w):
                self._unwatch(w)
                continue
            if w.live_due(now):
                self.book.save_live(w, now)
            if w.ended is not None:
                if now - w.ended > ENDED_WATCH_S:  # late rows of an ended run are still stored
                    self._unwatch(w)
                continue
            ending = self.book.decide(w, now, self._fill_gaps)
            if ending is not None:
                self._end(w, ending)
        every = self.reconcile_s if self.book.watches else 5 * self.reconcile_s
        if now - self._last_reconcile > every:
            self._last_reconcile = now
            self._reconcile(now)

    def _reconcile(self, now: float) -> None:
        """Stop services serving ended runs; resolve runs their services no longer serve."""
        assert self.bus is not None
        infos = {i["id"]: i for i in discover(self.bus, timeout=1.0)}
        for stale in stale_runs(infos, self.book.watches, self.store.run):
            log.info("%s: stopping it", stale)
            send_stop(self.bus, stale.run, stale.reason)
        wait_s = self.graces.unserved_s(self.reconcile_s)
        settle_s = self.graces.settle_s
        for w in list(self.book.watches.values()):
            if w.ended is None:
                ending = reconcile_run(w, infos, self.book.alive, now, settle_s, wait_s)
                if ending is not None:
                    self._end(w, ending)
                    continue
                lost = None
                if now - w.monitor.started > settle_s:
                    lost = start_lost(w.run, w.assign, w.attempt, infos, w.states, w.counts)
                if w.lost_start.due(lost is not None, now, settle_s):
                    self._start_again(w, f"{lost}: its start sent again")

    def _start_again(self, w: Watch, why: str) -> None:
        """Put the run's start again (`start_lost`), as its attempt on its assignment."""
        assert self.bus is not None
        row = self.store.run(w.run)
        if row is None or row["status"] != "running" or row.get("attempts") != w.attempt:
            return  # ended, or queued again, since the look
        try:
            config = make_config(row["config"])
        except ConfigError:
            return  # (a start of it was sent: it was read so then)
        log.warning("run %s: %s", w.run, why)
        send_start(self.bus, w.run, config, w.assign, w.attempt)

    def _reattach(self) -> None:
        """After a (re)start: follow the runs the store says are running, and store the
        points their evaluators published while nobody listened."""
        for run in self.book.to_follow(self.store.runs_with_status("running")):
            w = self._watch(run, time.monotonic())
            filled = self._fill_gaps(w)
            log.info("re-attached to run %s (%d points, %d filled)", w.run, w.points, filled)

    def _fill_gaps(self, w: Watch) -> int:
        """Ask the run's evaluator for every row it published; store the missing ones.

        Called after `_watch` has subscribed (so nothing falls between the two) and on
        the scheduler's thread (so these rows are stored before any that queue up
        meanwhile: points stay in episode order). The store ignores episodes it has.
        """
        bus = self.bus
        if bus is None:
            return 0
        got = history_rows(bus, w.run, self.history_timeout_s, w.attempt)
        rows = [flat_row(r) for r in got]
        return self.book.store_points(w.run, rows) if rows else 0

    # ------------------------------------------------------------ queries for HTTP
    def workers(self) -> list[dict[str, Any]] | None:
        """Live services (liveliness tokens) with their info; None when not connected."""
        bus = self.bus
        if bus is None or not self.connected.is_set():
            return None
        fresh = discover(bus, timeout=1.0)
        with self._lock:
            tokens = set(self._tokens)
            live = {peer for key in tokens if (peer := live_peer(key)) is not None}
            for info in fresh:
                self._infos[(info["role"], info["id"])] = info
            for peer in set(self._infos) - live:
                del self._infos[peer]
            infos = list(self._infos.values())
        return worker_rows(tokens, infos)
