"""What every service shares: its bus session, inbox, liveliness, run control, rejects.

A service is a loop on its own thread that drains an inbox filled by Zenoh
callbacks (callbacks only enqueue). Inbound payloads are decoded and validated by
`shared.net.wire`; a malformed message, a wrong schema version or a message for a run
the service does not serve is dropped, counted in `rejects` and logged (rate
limited), and the loop goes on. So is a message whose handling raises anything else
(`handler_failed`: its traceback logged once per exception type). `after_drain` runs
whenever the inbox is found empty after a burst of messages, for work a service does
once per burst.

Run control: `macb/control/start` carries the run id, its config and the
assignment of services (by id); a service takes a run only when it is named in the
assignment and is free, and never one whose id is no safe name (folders and keys are
built from it: `run_id_error`). `macb/control/stop` ends a run.

Restarts (docs/reliability.md): a service that takes a run writes it to
`DATA_DIR/services/ID.json`; started again with the same id and data dir (by `macb
up`'s supervisor, a container's restart policy, or by hand) it rejoins that run
(`on_resume`) instead of waiting for a new one. A peer whose liveliness token goes
away is given `MACB_PEER_GRACE_S` (30 s) to come back before the run is given up, so
a restarted service, or a restarted router (every token vanishes with it), costs a
pause, not the run.

The parts without the bus: `services/runs.py` (the runs served, which starts are
taken, the runs file), `services/peers.py` (peers away and their grace),
`services/inbox.py` (bursts, rejects). `ServiceBase` wires them to the bus and hooks.
"""

from __future__ import annotations

import faulthandler
import json
import logging
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from services.endpoint import Endpoint
from services.inbox import DRAINED, Inbox, Item, Rejects, reason_bucket, wake
from services.peers import PeerWatch
from services.runs import ServedRuns
from shared.config import ConfigError, TrainConfig, make_config
from shared.net import bus as keys
from shared.net.bus import Bus, Refused
from shared.net.info import ServiceInfo
from shared.net.messages import (
    MESSAGES,
    Ack,
    Assignment,
    Message,
    Start,
    Status,
    Stop,
    run_id_error,
    same_attempt,
)
from shared.net.monitor import peer_grace_s
from shared.net.wire import WireError, decode
from shared.settings import node_name, settings

M = TypeVar("M", bound=Message)
Reply = bytes | Refused | None  # what a query handler gives (`Bus.queryable`)


def restarts() -> int:
    """How many times this service was restarted (set by `macb up`'s supervisor)."""
    try:
        return settings().restarts
    except ValueError:
        return 0


def learner_end_reason(msg: Status) -> str:
    """Why a run ended, from its learner's decoded `status` message, for the status
    other services publish when they follow it (watchers show the first failure)."""
    return f"learner {msg.state}: {msg.reason or ''}".strip()


class ServiceHooks:
    """What a service does, as `ServiceBase` calls it: the hooks each service overrides
    (all of them optional), apart from the machinery that calls them, so a service's
    main.py reads as its answers to these events."""

    def start_replaces(self, run: str, attempt: int | None) -> bool:
        """A start for a run this service already serves, as `attempt` (the one served,
        or either not known): False ignores it (a repeated start); True means it begins
        a new attempt, and the service has let the old go."""
        return False

    def on_start(self, run: str, config: TrainConfig, assign: Assignment) -> None:
        """Take up `run` (its config, and the services assigned to it)."""

    def on_resume(self, run: str, config: TrainConfig, assign: Assignment) -> None:
        """Rejoin `run` after this process restarted; by default, as if it started."""
        self.on_start(run, config, assign)

    def on_stop(self, run: str, reason: str) -> None:
        """Let `run` go (stopped, or its learner gone); its status follows."""

    def on_learner_completed(self, run: str) -> None:
        """The run's learner completed (a follower that is done by then: nothing to do)."""

    def on_resume_retired(self, run: str, config: TrainConfig, assign: Assignment) -> None:
        """After a restart, before its other runs: a run of the group served that its
        `early_stop` rule ended while the others went on (`ServiceBase.retire`)."""

    def on_peer_found(self, role: str, peer: str) -> None:
        """A service's liveliness token appeared (it started, or came back)."""

    def handle(self, tag: str, key: str, payload: bytes) -> None:
        """A message the service listened for (`tag`), on the service's thread."""

    def tick(self) -> bool:
        """Work between messages; return True while more work is waiting (no idle wait)."""
        return False

    def after_drain(self) -> None:
        """The inbox is empty after one or more messages were handled: for work cheaper
        done once a burst than once a message (the counter counts a burst at once)."""

    def on_shutdown(self) -> None:
        """The process is ending while serving: flush what must survive a restart."""

    def on_peer_lost(self, role: str, peer: str) -> None:
        """A service's liveliness token vanished (it exited or was killed) and did not
        come back within the grace period."""


class ServiceBase(ServiceHooks):
    role = "service"
    # queue.SimpleQueue puts and gets much cheaper (C, no Python-level locks): worth it
    # where Zenoh's thread enqueues thousands of messages a second (the counter).
    inbox_type: type = queue.Queue
    max_runs = 1  # the counter serves many runs at once; the other services one
    # Rejoin the run served when the process died (the counter restores its own runs).
    rejoins = True
    # Actors and the evaluator work for one learner: its failure or loss ends their run.
    # The learner is that learner; the counter serves many runs and outlives learners.
    follows_learner = False
    tick_s = 0.05  # idle wait for messages when tick has nothing to do

    def __init__(self, service_id: str, connect: list[str] | None, data_dir: Path) -> None:
        self.id = service_id
        self.log = logging.getLogger(f"macb.{self.role}.{service_id}")
        self.data_dir = Path(data_dir)
        self.inbox: queue.Queue[Item] | queue.SimpleQueue[Item] = self.inbox_type()
        self.reject_tally = Rejects()
        # The reasons of handlers' exceptions whose traceback has been logged (once each).
        self._traced: set[str] = set()
        self._traced_lock = threading.Lock()
        self.rejects = self.reject_tally.by_reason  # read by the services' stats
        self.stop_event = threading.Event()
        runs_file = self.data_dir / "services" / f"{self.id}.json" if self.rejoins else None
        self.served = ServedRuns(self.max_runs, runs_file, self.log)
        self.active = self.served.active  # runs served now, with their configs
        self.finished = self.served.finished  # runs let go lately: late traffic expected
        self.peers = PeerWatch(peer_grace_s())  # peers whose liveliness token went away
        self.resumed: dict[str, Any] | None = None  # what on_resume restored, for info()
        self.bus = Bus(connect or keys.default_connect())
        self.endpoint = Endpoint(self.bus, self.inbox.put, self.id, self.role)
        # Subscriptions that enqueue (a run's end with it), statuses and metrics out.
        self.listen, self.subscribe = self.endpoint.listen, self.endpoint.subscribe
        # One subscription for both: a start and the stop sent after it arrive in that
        # order (Zenoh orders one subscription's messages, not several: "Order on the bus").
        self.listen(keys.k_control("*"), "control")
        self.answer(keys.k_info(self.role, self.id), self._info_reply)
        put = self.inbox.put
        self.bus.watch_liveliness(
            keys.k_live("*", "*"), lambda key, alive: put(("live", key, b"1" if alive else b"0"))
        )

    @property
    def assign(self) -> Assignment | None:
        """The services of the run served now (of the last run taken; None before any)."""
        return self.served.assign

    @property
    def grace_s(self) -> float:
        return self.peers.grace.grace_s

    # ------------------------------------------------------------ plumbing
    def reject(self, key: str, reason: str) -> None:
        """Drop a message: count it by reason and log it (at most once a second; the
        reason cut short, as its sender may have made it as long as it liked)."""
        total = self.reject_tally.add(reason, time.monotonic())
        if total is not None:
            self.log.warning(
                "dropped message on %.200s: %.300s (%d dropped so far)", key, reason, total
            )

    def decode_for_run(self, key: str, payload: bytes, expect: type[M]) -> M | None:
        """Decode a per-run message; None (and a counted reject) unless it is for our run.
        A status from another attempt of the run is dropped silently: late traffic of
        an ended attempt, as of a run let go. An ack of another attempt is dropped and
        counted: acks only move forward, and a counter that restored an ended attempt
        acks its positions every second, which would release batches it never counted."""
        return self.decode_or_why(key, payload, expect)[0]

    def decode_or_why(
        self, key: str, payload: bytes, expect: type[M]
    ) -> tuple[M | None, str | None]:
        """`decode_for_run`'s message, or None and the reject's reason (None when dropped
        silently): what a query's refusal tells its asker."""
        try:
            msg = decode(payload, expect)
        except WireError as err:
            self.reject(key, str(err))
            return None, str(err)
        why = self.served.refusal(keys.run_of(key), msg.run)
        if why:
            self.reject(key, why)
        if isinstance(msg, Status) and not self.of_attempt(msg.run, msg.attempt):
            return None, why
        if why is None and isinstance(msg, Ack) and not self.of_attempt(msg.run, msg.attempt):
            served = self.served.attempts.get(msg.run)
            why = f"ack of another attempt: {msg.service} acks {msg.attempt}, serving {served}"
            self.reject(key, why)
        return (msg, None) if why is None else (None, why)

    def of_attempt(self, run: str, attempt: int | None) -> bool:
        """Whether a message naming `attempt` may be of the attempt of `run` served."""
        return same_attempt(self.served.attempts.get(run), attempt)

    def publish_metrics(self, run: str, data: dict[str, Any], source: str | None = None) -> None:
        """A metric row or stats of `run`, stamped with the attempt served (its start's)."""
        self.endpoint.metrics(run, data, source, attempt=self.served.attempts.get(run))

    def publish_status(self, run: str, state: str, **fields: Any) -> None:
        """The service's status in `run`, stamped with the attempt it serves (its start's)
        unless `attempt` is given."""
        fields.setdefault("attempt", self.served.attempts.get(run))
        self.endpoint.status(run, state, **fields)

    def serves(self, run: str) -> bool:
        return run in self.active

    @property
    def run_id(self) -> str | None:
        """The run served (the first one, for multi-run services), or None when free."""
        return next(iter(self.active), None)

    @property
    def config(self) -> TrainConfig | None:
        return self.active.get(self.run_id) if self.run_id else None

    def info(self) -> ServiceInfo:
        rejects, total = self.reject_tally.counts()
        return ServiceInfo(
            id=self.id,
            role=self.role,
            run=self.run_id,
            runs=list(self.active),
            rejects=rejects,
            rejects_total=total,
            restarts=restarts(),
            resumed=self.resumed,
            node=node_name(),
        )

    def _info_reply(self, key: str, payload: bytes) -> bytes:
        return json.dumps(self.info().to_json()).encode()

    # ------------------------------------------------------------ control
    def _on_control(self, tag: str, key: str, payload: bytes) -> None:
        if tag not in ("start", "stop"):
            self.reject(key, f"unknown control message: {tag:.40}")
            return
        try:
            msg = decode(payload, MESSAGES[tag])
        except WireError as err:
            self.reject(key, str(err))
            return
        run = msg.run
        if isinstance(msg, Stop):
            if self.serves(run):  # else a run served by other services: not ours to stop
                self.log.info("stopping run %s: %s", run, msg.reason)
                self._end(run, "stopped", msg.reason)
            return
        assert isinstance(msg, Start)
        if why := run_id_error(run):
            # Every service builds folders and keys from the id (the learner wipes
            # data_dir/learner/<run>): refused here, once for all of them, and no status
            # goes out on a key built from it.
            self.reject(key, why)
            return
        if not self.assigned(msg.assign):
            return  # another service's run: not an error
        let_go = run not in self.active and run in self.finished
        if let_go and msg.attempt is not None and msg.attempt == self.served.attempts.get(run):
            # Sent again for a service that missed it (shared.net.monitor.start_lost)
            # after this one had done its part: the attempt is over here. (A retry names
            # its new attempt; a starter that numbers none may start a run id again.)
            self.log.info("run %s: start of attempt %s, let go already: ignored", run, msg.attempt)
            return
        if run in self.active and not self.of_attempt(run, msg.attempt):
            # Its stop never came (lost while a router restarted, say): the attempt
            # served is over, and its end is published as its own (the new one's
            # watchers drop it). The counter, which a retry may get while still
            # serving the old attempt, then counts the new one from nothing.
            old = self.served.attempts.get(run)
            self.log.warning(
                "run %s: attempt %s started while serving attempt %s", run, msg.attempt, old
            )
            self._end(run, "stopped", f"attempt {msg.attempt} of the run started")
        elif run in self.active and not self.start_replaces(run, msg.attempt):
            return  # repeated start: idempotent
        if self.served.full() and not self.joins_group(run, msg.assign):
            self.log.warning("asked to start %s while serving %s: ignored", run, self.run_id)
            return
        try:
            config = make_config(msg.config)
        except ConfigError as err:
            self.reject(key, f"bad config: {err}")
            why = f"invalid config: {err}"
            self.publish_status(run, "failed", reason=why, attempt=msg.attempt)
            return
        self.log.info("starting run %s", run)
        self._join(run, config, msg.assign, msg.config, self.on_start, msg.attempt)

    def _join(
        self,
        run: str,
        config: TrainConfig,
        assign: Assignment,
        raw: dict,
        hook: Callable[[str, TrainConfig, Assignment], None],
        attempt: int | None = None,
    ) -> None:
        """Take the run (`hook` is on_start, or on_resume after a restart) as its
        `attempt`, and note it in the service's file, so that a restarted process
        rejoins it."""
        self.served.join(run, config, assign, raw, attempt)
        if self.follows_learner:
            self.listen(keys.k_status(run, assign.learner), "learner_status", run)
        try:
            hook(run, config, assign)
        except Exception as err:
            self.log.exception("run %s failed to start", run)
            self.publish_status(run, "failed", reason=f"{type(err).__name__}: {err}")
            self.free(run)
            return
        if run in self.active:
            self.served.save()

    def _rejoin(self) -> None:
        """After a restart: rejoin the run (or the group's runs) served when the process died."""
        saved = self.served.saved()
        for s in saved:  # (retired runs first: the group is whole once the others come)
            if s.retired:
                self.served.retired[s.run] = (s.raw, s.assign)
                self.served.attempts[s.run] = s.attempt
                self.on_resume_retired(s.run, s.config, s.assign)
        for s in saved:
            if not s.retired:
                self.log.info("rejoining run %s after a restart (from %s)", s.run, self.served.path)
                self._join(s.run, s.config, s.assign, s.raw, self.on_resume, s.attempt)

    def _on_learner_status(self, key: str, payload: bytes) -> None:
        """The run's learner failed or was stopped: this service's part is over too."""
        msg = self.decode_for_run(key, payload, Status)
        if msg is not None and msg.state == "completed":
            self.on_learner_completed(msg.run)
        elif msg is not None and msg.state in ("failed", "stopped"):
            self._end(msg.run, "stopped", learner_end_reason(msg))

    def _end(self, run: str, state: str, reason: str) -> None:
        """Give a run up: the service's hook, its status for the watchers, then free."""
        self.on_stop(run, reason)
        self.publish_status(run, state, reason=reason)
        self.free(run)

    def joins_group(self, run: str, assign: Assignment) -> bool:
        """A start for another run of the group this service serves."""
        return self.served.joins_group(run, assign)

    def assigned(self, assign: Assignment) -> bool:
        return assign.names(self.role, self.id)

    def free(self, run: str) -> None:
        """Forget a run: the service is free for the next one."""
        self.endpoint.drop_run(run)
        self.served.leave(run)
        self.served.save()
        if not self.active:
            self.peers.clear()
            self.resumed = None

    def retire(self, run: str) -> None:
        """A group's run its `early_stop` rule ended while the others go on: no longer
        served (its subscriptions end), still noted for a restart (`ServedRuns.retire`)."""
        self.endpoint.drop_run(run)
        self.served.retire(run)
        self.served.save()

    def _peer_event(self, key: str, alive: bool) -> None:
        seen = self.peers.seen(key, alive, time.monotonic()) if self.active else None
        if seen is not None and seen.back:
            self.log.info("%s %s is back", seen.role, seen.peer)
        if seen is not None and alive:
            self.on_peer_found(seen.role, seen.peer)

    def on_peer_lost(self, role: str, peer: str) -> None:
        """A peer gone past the grace period. A service that follows its run's learner
        gives the run up as failed when the learner is gone: without it no credits,
        weights or evaluation points can come."""
        ours = self.assign is not None and self.assign.learner == peer
        if role == "learner" and self.follows_learner and ours:
            for run in list(self.active):  # the run, or every run of its group
                self.log.error("run %s: learner %s is gone; giving the run up", run, peer)
                why = f"learner {peer} is gone (not back within {self.grace_s:g} s)"
                self._end(run, "failed", why)

    # ------------------------------------------------------------ loop
    def serve_forever(self) -> None:
        inbox, busy = Inbox(self.inbox), False
        try:
            self._rejoin()
            # Announced only now, every subscription of the service (and of a run it
            # rejoined) in place: what peers send when they see it arrives.
            self.bus.token(keys.k_live(self.role, self.id))
            while not self.stop_event.is_set():
                if self.active:
                    for role, peer in self.peers.given_up(time.monotonic()):
                        self.on_peer_lost(role, peer)
                item = inbox.take(busy, self.tick_s)
                if item == DRAINED:
                    self.after_drain()
                    continue  # tick ran after the last message; wait as before
                if item is not None:
                    self._dispatch(*item)
                busy = bool(self.tick())
        finally:
            self.shutdown()

    def _dispatch(self, tag: str, key: str, payload: bytes) -> None:
        try:
            if tag == "control":
                self._on_control(key.rsplit("/", 1)[-1], key, payload)
            elif tag == "learner_status":
                self._on_learner_status(key, payload)
            elif tag == "live":
                self._peer_event(key, payload == b"1")
            else:
                self._handle_data(tag, key, payload)
        except WireError as err:
            self.reject(key, str(err))

    def _handle_data(self, tag: str, key: str, payload: bytes) -> None:
        """A data message (`handle`): one whose handling raises is dropped and counted
        (`handler_failed`). Not the service's own failures: a disk or memory error
        ends the process, whose restart goes on from its files (dropped, a batch whose
        log write failed was acknowledged all the same), and a control message's
        handling, which may have changed a run halfway, ends it too."""
        try:
            self.handle(tag, key, payload)
        except (WireError, OSError, MemoryError):
            raise
        except Exception as err:
            self.handler_failed(key, err)

    def handler_failed(self, key: str, err: Exception) -> None:
        """A message's handling raised (content the checks let through, or a bug it
        hit): a message must not end the service, so it is dropped like a malformed
        one, counted under a reason naming the exception's type, and the traceback is
        logged the first time that reason comes (then at the rejects' rate)."""
        reason = f"handler raised {type(err).__name__}: {err}"
        with self._traced_lock:
            first = reason_bucket(reason) not in self._traced
            self._traced.add(reason_bucket(reason))
        if first:
            self.log.error("handling a message on %.200s raised", key, exc_info=err)
        self.reject(key, reason)

    def answer(self, key_expr: str, handler: Callable[[str, bytes], Reply]) -> None:
        """Declare a queryable on `key_expr`; `handler` runs on Zenoh's thread. Its
        exception is the query's refusal, naming the exception's type (the asker counts it
        apart from silence, rather than waiting out its timeout and asking again), and a
        dropped message of the service (`handler_failed`: counted, its traceback logged
        the first time), rather than a traceback per query."""

        def guarded(key: str, payload: bytes) -> Reply:
            try:
                return handler(key, payload)
            except Exception as err:
                self.handler_failed(key, err)
                return Refused(self.id, f"handler raised {type(err).__name__}")

        self.bus.queryable(key_expr, guarded)

    def shutdown(self) -> None:
        """Flush what must survive (hook), then close the session."""
        try:
            if self.active:
                self.on_shutdown()
        finally:
            self.bus.close()


# A service still alive this long after SIGTERM or SIGINT writes every thread's stack to
# its log (stderr): a shutdown that hangs says where, before a supervisor's SIGKILL.
SHUTDOWN_STACKS_AFTER_S = 8.0


def stop_on_signals(service: ServiceBase) -> None:
    """SIGTERM and SIGINT end the service's loop; `shutdown` then flushes and closes.
    SIGUSR1 writes every thread's stack to the log and the service goes on (a service
    that seems stuck says where, as `py-spy dump` would without installing it)."""

    def handler(signum: int, frame: object) -> None:
        service.log.info("signal %d: shutting down", signum)
        faulthandler.dump_traceback_later(SHUTDOWN_STACKS_AFTER_S, file=sys.stderr)
        service.stop_event.set()
        wake(service.inbox)

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)
    faulthandler.register(signal.SIGUSR1, file=sys.stderr, all_threads=True)
