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
  told to stop it, so it is free again.
- Sends the stop messages the HTTP side asks for (a failed run's other services are
  stopped too, so they are free for the next run).
- On start (after an API restart), re-attaches to the runs the store says are
  running and asks each run's evaluator for the rows it published meanwhile
  (`macb/run/{run}/history/eval`), so no point is lost while the API is down; a run
  whose services no longer serve it ended while nobody listened, and is resolved
  from what was stored. At a run's end, rows still missing are asked for once more.
- A run queued again (POST /experiments/{id}/retry) starts afresh: what the attempt
  that ended still sends (late rows, statuses) is not stored on the queued run.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from services.common import restarts
from shared.config import ConfigError, TrainConfig, make_config
from shared.groups import group_error, group_key
from shared.net import bus as keys
from shared.net.bus import Bus
from shared.net.control import (
    NoFreeServices,
    assign_services,
    discover,
    history_rows,
    send_start,
    send_stop,
)
from shared.net.messages import Metrics, Status
from shared.net.monitor import Graces, RunMonitor
from shared.net.monitor import peer_grace_s as peer_grace
from shared.net.wire import WireError, decode

from .store import Store

log = logging.getLogger("macb.api.scheduler")


def flat_row(data: dict[str, Any]) -> dict[str, Any]:
    """The JSON-safe part of a message's map: string keys, plain finite values."""
    out: dict[str, Any] = {}
    for k, v in data.items():
        if not isinstance(k, str):
            continue
        if isinstance(v, float) and not math.isfinite(v):
            v = None
        elif isinstance(v, list):
            v = [
                x
                for x in v
                if isinstance(x, str | int) or (isinstance(x, float) and math.isfinite(x))
            ]
        elif isinstance(v, dict):
            v = flat_row(v)
        elif not isinstance(v, str | int | float | bool | type(None)):
            continue
        out[k] = v
    return out


@dataclass
class Watch:
    """What the scheduler holds for one running run."""

    run: str
    assign: dict[str, Any]
    episodes: int
    monitor: RunMonitor  # the rule that ends it, fed with its events
    subs: list[Any] = field(default_factory=list)
    live: dict[str, Any] = field(default_factory=dict)
    live_dirty: bool = False
    live_written: float = 0.0
    last_episode: int = 0
    unserved_since: float | None = None
    ended: float | None = None  # monotonic time it reached a final status
    notes: list[str] = field(default_factory=list)  # resumes: kept as the run's reason

    @property
    def states(self) -> dict[str, dict[str, Any]]:
        return self.monitor.states

    @property
    def points(self) -> int:
        return self.monitor.points

    def services(self) -> list[tuple[str, str]]:
        return self.monitor.services()


class Scheduler:
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
        self.counter_grace_s = counter_grace_s
        self.start_timeout_s = start_timeout_s
        self.completion_grace_s = completion_grace_s
        self.reconcile_s = reconcile_s
        self.history_timeout_s = history_timeout_s
        self.peer_grace_s = peer_grace() if peer_grace_s is None else peer_grace_s
        self.events: queue.Queue[tuple[str, str, Any]] = queue.Queue()
        self.bus: Bus | None = None
        self.connected = threading.Event()
        self.watches: dict[str, Watch] = {}
        self.alive: set[tuple[str, str]] = set()  # (role, id) with a liveliness token
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._main, name="macb-api-scheduler", daemon=True)
        self._last_reconcile = 0.0
        self._last_assign_try = 0.0
        self.listeners: list[Callable[[], None]] = []  # called after the store changed

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
                for w in self.watches.values():
                    w.subs.clear()
                self.watches.clear()
                with contextlib.suppress(Exception):
                    self.bus.close()
                self.bus = None

    def _serve(self) -> None:
        bus = self.bus
        assert bus is not None
        bus.token(keys.k_live("api", self.service_id))
        bus.queryable(keys.k_info("api", self.service_id), self._info_reply)
        bus.watch_liveliness(
            keys.k_live("*", "*"), lambda key, up: self.events.put(("live", key, up))
        )
        self.connected.set()
        log.info("scheduler connected to %s", self.connect)
        self._reattach()
        while not self._stop.is_set():
            self._drain(timeout=self.tick_s)
            self._send_stops()
            self._assign_queued()
            self._check_runs()

    def _info_reply(self, key: str, payload: bytes) -> bytes:
        return json.dumps(
            {
                "id": self.service_id,
                "role": "api",
                "run": None,
                "runs": [],
                "rejects": {},
                "rejects_total": 0,
                "restarts": restarts(),
                "http": self.http_url,
            }
        ).encode()

    def _changed(self) -> None:
        for fn in self.listeners:
            with contextlib.suppress(Exception):
                fn()

    # ------------------------------------------------------------ events
    def _drain(self, timeout: float) -> None:
        """Handle every queued bus event; wait up to `timeout` for the first."""
        try:
            first = self.events.get(timeout=timeout)
        except queue.Empty:
            return
        batch = [first]
        with contextlib.suppress(queue.Empty):
            while len(batch) < 10_000:
                batch.append(self.events.get_nowait())
        rows: dict[str, list[dict[str, Any]]] = {}
        for kind, key, payload in batch:
            try:
                if kind == "metrics":
                    self._on_metrics(key, payload, rows)
                elif kind == "status":
                    self._on_status(key, payload)
                elif kind == "live":
                    self._on_live(key, payload)
            except Exception:  # one odd message must not stop the bookkeeping
                log.exception("dropped a %s event on %s", kind, key)
        for run, new in rows.items():
            self._store_points(run, new)
        if rows:
            self._changed()

    def _superseded(self, w: Watch) -> bool:
        """The watch's run ended and was queued again since (a retry): what its ended
        attempt still sends belongs to no attempt the store keeps. A look-up only for
        ended watches, which live 3 s."""
        if w.ended is None:
            return False
        row = self.store.run(w.run)
        return row is None or row["status"] == "queued"

    def _store_points(self, run: str, rows: list[dict[str, Any]]) -> int:
        """Store evaluation rows (the store ignores episodes it has); count the new ones
        on the run's watch. Returns how many were new."""
        w = self.watches.get(run)
        if w is not None and self._superseded(w):
            return 0
        added = self.store.add_points(run, rows)
        if w is not None and added:
            w.monitor.points_seen(added)
            w.last_episode = max([w.last_episode] + [int(r["episode"]) for r in rows])
        return added

    def _on_metrics(self, key: str, payload: bytes, rows: dict[str, list]) -> None:
        run = keys.run_of(key)
        w = self.watches.get(run or "")
        if w is None:
            return
        try:
            msg = decode(payload, Metrics)
        except WireError:
            return
        if msg.run != run:
            return
        data = flat_row(msg.data)
        if msg.source == "eval":
            if isinstance(data.get("episode"), int):
                rows.setdefault(run, []).append(data)
                w.live["eval"] = data
                w.live_dirty = True
        else:
            w.live[msg.source] = data
            w.live_dirty = True

    def _on_status(self, key: str, payload: bytes) -> None:
        run = keys.run_of(key)
        w = self.watches.get(run or "")
        if w is None:
            return
        try:
            msg = decode(payload, Status)
        except WireError:
            return
        if msg.run != run or self._superseded(w):
            return
        w.monitor.status(msg.service, msg.state, flat_row(msg.detail), time.monotonic())
        resumed = msg.detail.get("resumed")
        if msg.service == w.assign["learner"] and isinstance(resumed, dict):
            cut = resumed.get("from_episode")
            where = f"the cut at episode {cut}" if cut is not None else "its log (no cut yet)"
            note = f"learner {msg.service} restarted and resumed from {where}"
            if note not in w.notes:
                w.notes.append(note)
                log.info("run %s: %s", w.run, note)
                self.store.set_reason(w.run, "; ".join(w.notes))
        self.store.set_services(w.run, w.states)
        self._changed()

    def _on_live(self, key: str, up: bool) -> None:
        parts = key.split("/")
        if len(parts) != 4:
            return
        role, sid = parts[2], parts[3]
        if up:
            self.alive.add((role, sid))
            self._wake.set()
        else:
            self.alive.discard((role, sid))
        now = time.monotonic()
        for w in list(self.watches.values()):
            if w.ended is not None:
                continue
            before = w.monitor.waiting()
            w.monitor.peer(role, sid, up, now)
            self._show_waiting(w, before)

    def _show_waiting(self, w: Watch, before: str | None) -> None:
        """The run's reason says what it waits for (a service to come back), else its notes."""
        waiting = w.monitor.waiting()
        if waiting != before:
            if before is not None and waiting is None:
                log.info("run %s: back (%s no longer)", w.run, before)
            self.store.set_reason(w.run, waiting or "; ".join(w.notes) or None)
            self._changed()

    def _watch(self, run: dict[str, Any], started: float) -> Watch:
        bus = self.bus
        assert bus is not None
        old = self.watches.get(run["id"])
        if old is not None:  # the ended attempt of a run queued again
            self._unwatch(old)
        stats = self.store.point_stats([run["id"]])[run["id"]]
        graces = Graces(
            peer_s=self.peer_grace_s,
            counter_s=self.counter_grace_s,
            completion_s=self.completion_grace_s,
            start_s=self.start_timeout_s,
        )
        monitor = RunMonitor(run["assign"], started, graces, run.get("services"), stats[0])
        w = Watch(
            run=run["id"],
            assign=run["assign"],
            episodes=int(run["config"].get("episodes", 0)),
            monitor=monitor,
            live=dict(run.get("live") or {}),
            last_episode=stats[2],
        )
        put = self.events.put
        w.subs.append(
            bus.subscribe(keys.k_metrics(w.run, "**"), lambda k, p: put(("metrics", k, p)))
        )
        w.subs.append(bus.subscribe(keys.k_status(w.run, "*"), lambda k, p: put(("status", k, p))))
        self.watches[w.run] = w
        return w

    def _unwatch(self, w: Watch) -> None:
        if self.bus is not None:
            for h in w.subs:
                self.bus.undeclare(h)
        w.subs.clear()
        self.watches.pop(w.run, None)

    def _end(self, w: Watch, status: str, reason: str | None, stop: bool) -> None:
        """Record a final status; with `stop`, tell the run's services to stop."""
        if w.live_dirty:
            self.store.set_live(w.run, w.live)
            w.live_dirty, w.live_written = False, time.monotonic()
        if reason is None and w.notes:
            reason = "; ".join(w.notes)
        if self.store.finish(w.run, status, reason, stop_sent=not stop):
            log.info("run %s %s%s", w.run, status, f": {reason}" if reason else "")
        if stop:
            self._send_stops()
        w.ended = time.monotonic()
        self._wake.set()  # its services are free for a queued run
        self._changed()

    def _fail(self, w: Watch, reason: str) -> None:
        self._end(w, "failed", reason, stop=True)

    def _send_stops(self) -> None:
        if self.bus is None:
            return
        for run, reason in self.store.stops_to_send():
            send_stop(self.bus, run, reason)
            self.store.stop_sent(run)
            w = self.watches.get(run)
            if w is not None and w.ended is None:
                w.ended = time.monotonic()

    def _reserved(self) -> set[str]:
        """Services of runs we started that are not over yet."""
        busy: set[str] = set()
        for w in self.watches.values():
            if w.ended is not None:
                continue
            busy.add(w.assign["learner"])
            busy.add(w.assign["evaluator"])
            busy.update(w.assign.get("actors", []))
        return busy

    def _assign_queued(self) -> None:
        now = time.monotonic()
        if now - self._last_assign_try < 1.0 and not self._wake.is_set():
            return
        self._wake.clear()
        queued = self.store.runs_with_status("queued")
        if not queued:
            return
        self._last_assign_try = now
        assert self.bus is not None
        infos = discover(self.bus, timeout=1.0)
        reserved = self._reserved()
        for info in infos:
            if info["role"] != "counter" and info["id"] in reserved:
                info["run"] = info.get("run") or "(reserved)"
        waiting: dict[str, str] = {}
        refused: dict[int, str] = {}  # actors needed -> why not (for this pass)
        grouped: set[str] = set()  # queued runs started in a group this pass
        for run in queued:
            if run["id"] in grouped:
                continue
            if run["actors"] in refused:
                if run["reason"] != refused[run["actors"]]:
                    waiting[run["id"]] = refused[run["actors"]]
                continue
            try:
                assign = assign_services(infos, run["actors"])
            except NoFreeServices as err:
                refused[run["actors"]] = f"waiting: {err}"
                if run["reason"] != refused[run["actors"]]:
                    waiting[run["id"]] = refused[run["actors"]]
                continue
            try:
                config = make_config(run["config"])
            except ConfigError as err:  # stored by an older API with other rules
                self.store.finish(run["id"], "failed", f"invalid config: {err}")
                continue
            members = self._group_of(run, config, queued, grouped)
            if len(members) > 1:
                assign["group"] = [m["id"] for m, _ in members]
            if not self.store.claim_all([m["id"] for m, _ in members], assign):
                continue  # stopped meanwhile
            for member, _ in members:
                member["assign"] = assign
                member["services"], member["live"] = {}, {}  # a new attempt: no states yet
                self._watch(member, time.monotonic())
            for member, member_config in members:
                send_start(self.bus, member["id"], member_config, assign)
            grouped.update(m["id"] for m, _ in members)
            log.info("run %s started on %s", assign.get("group", run["id"]), assign)
            taken = {assign["learner"], assign["evaluator"], *assign["actors"]}
            for info in infos:
                if info["id"] in taken and info["role"] != "counter":
                    info["run"] = run["id"]
            self._changed()
        self.store.set_waiting(waiting)

    def _group_of(
        self,
        run: dict[str, Any],
        config: TrainConfig,
        queued: list[dict[str, Any]],
        taken: set[str],
    ) -> list[tuple[dict[str, Any], TrainConfig]]:
        """`run` and the queued runs of its experiment that can share its group (in
        queue order, at most `group_size`); just `run` when it cannot lead one."""
        members = [(run, config)]
        if self.group_size < 2 or group_error([config], run["actors"]) is not None:
            return members
        key = group_key(config)
        for other in queued:
            if len(members) >= self.group_size:
                break
            if other["id"] == run["id"] or other["id"] in taken:
                continue
            if other["experiment_id"] != run["experiment_id"] or other["actors"] != 1:
                continue
            try:
                other_config = make_config(other["config"])
            except ConfigError:
                continue  # refused when its own turn comes
            if group_key(other_config) == key and not group_error([other_config], 1):
                members.append((other, other_config))
        return members

    def _check_runs(self) -> None:
        now = time.monotonic()
        for w in list(self.watches.values()):
            if self._superseded(w):
                self._unwatch(w)
                continue
            if w.live_dirty and (now - w.live_written > 1.0 or w.ended is not None):
                self.store.set_live(w.run, w.live)
                w.live_dirty, w.live_written = False, now
                self._changed()
            if w.ended is not None:
                if now - w.ended > 3.0:  # late rows of an ended run are still stored
                    self._unwatch(w)
                continue
            self._decide(w, now)
        every = self.reconcile_s if self.watches else 5 * self.reconcile_s
        if now - self._last_reconcile > every:
            self._last_reconcile = now
            self._reconcile(now)

    def _decide(self, w: Watch, now: float) -> None:
        row = self.store.run(w.run)
        if row is None or row["status"] != "running":
            w.ended = w.ended or now  # stopped over HTTP
            return
        before = w.monitor.waiting()
        decision = w.monitor.decide(now)
        if decision.ask_history:
            self._fill_gaps(w)
            decision = w.monitor.decide(now)
        if decision.state == "failed":
            self._fail(w, decision.reason or "failed")
        elif decision.state == "stopped":
            self._end(w, "stopped", decision.reason, stop=True)
        elif decision.state == "completed":
            self._end(w, "completed", decision.reason, stop=False)
        else:
            self._show_waiting(w, before)

    def _reconcile(self, now: float) -> None:
        """Runs whose services no longer serve them, with no end seen: resolve them."""
        assert self.bus is not None
        infos = {i["id"]: i for i in discover(self.bus, timeout=1.0)}
        self._stop_stale(infos)
        for w in list(self.watches.values()):
            if w.ended is not None or now - w.monitor.started < self.start_timeout_s / 4:
                continue
            # Not the counter: it serves many runs and resumes those it had from disk
            # when it restarts, including one whose learner is gone for good.
            serving = [
                sid
                for role, sid in w.services()
                if role != "counter"
                and sid in infos
                and (infos[sid].get("run") == w.run or w.run in (infos[sid].get("runs") or []))
            ]
            learner = w.assign["learner"]
            if ("learner", learner) not in self.alive and learner not in infos:
                w.monitor.peer("learner", learner, False, now)  # gone unseen: the same grace
            if serving:
                w.unserved_since = None
                continue
            if w.unserved_since is None:
                w.unserved_since = now
                continue
            if now - w.unserved_since < max(self.reconcile_s, self.peer_grace_s):
                continue  # restarted services take a while to rejoin
            if w.last_episode >= w.episodes and w.episodes > 0:
                self._end(
                    w, "completed", "its end was not observed (the API was not listening)", False
                )
            else:
                self._fail(
                    w,
                    "its services no longer serve it and no end was seen (it ended while the "
                    f"API was not listening); last point stored: episode {w.last_episode}",
                )

    def _stop_stale(self, infos: dict[str, dict[str, Any]]) -> None:
        """Services that rejoined (after a restart) a run that has ended: stop it."""
        assert self.bus is not None
        for info in infos.values():
            run = info.get("run")
            if info.get("role") == "counter" or not run or run in self.watches:
                continue
            row = self.store.run(run)
            if row is not None and row["status"] in ("completed", "failed", "stopped"):
                log.info(
                    "%s %s serves run %s, which has %s: stopping it",
                    info["role"],
                    info["id"],
                    run,
                    row["status"],
                )
                send_stop(self.bus, run, f"the run had {row['status']} while this service was down")

    def _reattach(self) -> None:
        """After a (re)start: follow the runs the store says are running, and store the
        points their evaluators published while nobody listened."""
        running = self.store.runs_with_status("running")
        for run in running:
            if run["id"] in self.watches or not run.get("assign"):
                continue
            w = self._watch(run, time.monotonic())
            filled = self._fill_gaps(w)
            log.info(
                "re-attached to run %s (%d points stored, %d of them filled from the "
                "evaluator's history)",
                w.run,
                w.points,
                filled,
            )

    def _fill_gaps(self, w: Watch) -> int:
        """Ask the run's evaluator for every row it published; store the missing ones.

        Called after `_watch` has subscribed (so nothing falls between the two) and on
        the scheduler's thread (so these rows are stored before any that queue up
        meanwhile: points stay in episode order). The store ignores episodes it has.
        """
        bus = self.bus
        if bus is None:
            return 0
        rows = [flat_row(r) for r in history_rows(bus, w.run, self.history_timeout_s)]
        if not rows:
            return 0
        added = self._store_points(w.run, rows)
        if added:
            self._changed()
        return added

    # ------------------------------------------------------------ queries for HTTP
    def workers(self) -> list[dict[str, Any]] | None:
        """Live services (liveliness tokens) with their info; None when not connected."""
        bus = self.bus
        if bus is None or not self.connected.is_set():
            return None
        tokens = bus.alive(keys.k_live("*", "*"), timeout=1.0)
        infos = {(i["role"], i["id"]): i for i in discover(bus, timeout=1.0)}
        out = []
        for key in sorted(set(tokens)):
            parts = key.split("/")
            if len(parts) != 4:
                continue
            role, sid = parts[2], parts[3]
            info = infos.get((role, sid))
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
