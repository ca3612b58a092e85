"""The counter service: the count tables of every active run, exactly once per transition.

It owns the tables because counts must change only on collection, once per transition,
whoever else sees the transitions: every run's batches are taken by the learner's
receive rule (`shared.net.protocol.ReceiveCursor` of the run's actors, whole batches:
duplicates ignored, gaps and overlaps dropped for the actor to resend; a batch of one
episode, one step in lockstep), so that every row counted is one the learner can take
into replay, then hashed in bursts, written to a write-ahead log and only then counted
and acknowledged, so an acknowledged count survives a SIGKILL.
Bonus queries are answered on Zenoh's thread under the lock ingestion takes, so a
query sees a burst counted whole or not at all, and they come first (a short GIL
switch interval, the service thread stepping aside): the learner waits for them. A
query of another attempt of the run than the one whose tables it holds is refused
(a run restored from disk answers only its noted attempt's learner, until a start of
another attempt replaces it), and every reply names this counter.

This class is the shell: the bus, the timers and the dispatch. Its parts: `runs.py`
(the runs' folders, opened, restored, archived; the lock), `burst.py` (a burst's new
rows, counted), `bonus.py` (queries answered), `snapshot.py` (snapshot.pt and the log
replayed), `stats.py` (what is reported), `state.py` (`RunState`).

Durability (files, snapshot schedule, restore) is in docs/architecture.md, "The
counter's files"; why the burst sizes, switch interval and snapshot spacing are what
they are is in docs/performance.md, "Counter service".
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import sys
import time
from pathlib import Path
from typing import Any

from services.common import ServiceBase, learner_end_reason
from services.counter import bonus, burst, snapshot
from services.counter.runs import Runs, keys_held
from services.counter.state import RunState
from services.counter.stats import run_stats, update_rate
from shared.config import TrainConfig
from shared.net.bus import Refused, k_ack, k_bonus, k_status, k_transitions, run_of
from shared.net.info import CounterInfo, ServiceInfo
from shared.net.messages import Ack, Assignment, BonusQuery, Status, Transitions, is_service_id
from shared.net.wire import WireError, check_batch_rows, check_dims, encode
from shared.settings import settings

STATS_S = 1.0


class CounterService(ServiceBase):
    role = "counter"
    inbox_type = queue.SimpleQueue  # thousands of batches a second go through it
    max_runs = 1_000_000  # it owns the tables of every active run
    rejoins = False  # it restores every unfinished run from its own files (Runs.restore_all)

    def __init__(
        self,
        service_id: str,
        connect: list[str] | None,
        data_dir: Path,
        snapshot_s: float | None = None,
        stats_s: float = STATS_S,
    ) -> None:
        # Set before the base class declares the info queryable (it calls info()).
        log = logging.getLogger(f"macb.{self.role}.{service_id}")  # the base's, made early
        self.runs = Runs(Path(data_dir) / "counter", log)
        self._ready = False
        self.pending = burst.Pending()  # batches checked, not taken yet
        self.queries = bonus.QueryGate()  # bonus queries being answered now
        if snapshot_s is None:
            snapshot_s = settings().counter_snapshot_s  # MACB_COUNTER_SNAPSHOT_S
        self.snapshot_s = snapshot_s
        self.stats_s = stats_s
        super().__init__(service_id, connect, data_dir)
        self.root = self.runs.root
        self.root.mkdir(parents=True, exist_ok=True)
        # Subscribe before restoring: batches arriving meanwhile wait in the inbox.
        self.listen(k_transitions("*", "*"), "transitions")
        self.listen(k_status("*", "*"), "status")
        for run, config, st in self.runs.restore_all():
            self.active[run] = config
            self.served.attempts[run] = self.runs.attempt(run)
            self.publish_status(run, "running", restored=True, counted=st.counted)
            self._ack(run, st)
        self.answer(k_bonus("*"), self._on_bonus)
        now = time.monotonic()
        self._next_stats = now + self.stats_s
        self._next_snapshot = now + self.snapshot_s
        self._ready = True
        self.log.info("counter %s ready (data in %s)", self.id, self.root)

    # ------------------------------------------------------------ run lifecycle
    def on_start(self, run: str, config: TrainConfig, assign: Assignment) -> None:
        path = self.runs.prepare(run, config, assign, self.served.attempts.get(run))
        st, replayed = self.runs.open(run, config, path)
        if replayed or st.counted:
            self.log.info(
                "resumed run %s: %d counted, %d keys, %d WAL records replayed",
                run,
                st.counted,
                keys_held(st),
                replayed,
            )
        else:
            self.log.info(
                "started run %s: %s %s k=%d, %d table(s)",
                run,
                config.task,
                config.explore,
                config.k,
                len(st.explorer.tables),
            )
        self.publish_status(run, "running", counted=st.counted)

    def start_replaces(self, run: str, attempt: int | None) -> bool:
        """A start for a run resumed from disk at startup: the run was queued again (its
        earlier attempt ended while this counter was down, so no stop reached it). Its
        old tables and expected numbers must not meet the new attempt's transitions,
        numbered from 0 again: stop the old state (archived by on_start) and start anew.
        A start naming the attempt restored (attempt.json) is that attempt's again, and
        a run started in this process ignores a repeated start, as every service does."""
        if run not in self.runs.restored:
            return False
        if attempt is not None and attempt == self.served.attempts.get(run):
            self.log.info("run %s: attempt %s started again: already restored", run, attempt)
            return False
        self.log.warning("run %s: started again while restored from disk: a new attempt", run)
        self.on_stop(run, "a new attempt of the run started")
        self.free(run)
        return True

    def on_stop(self, run: str, reason: str) -> None:
        st = self.runs.get(run)
        if st is None:
            return
        self._take_burst()  # what arrived before the stop is in the final snapshot
        self.runs.mark_stopped(run, st, reason)
        self.log.info(
            "stopped run %s (%s): %d counted, %d keys", run, reason, st.counted, keys_held(st)
        )

    def free(self, run: str) -> None:
        self.runs.close(run)
        super().free(run)

    def on_shutdown(self) -> None:
        self._take_burst()
        runs = self.runs.items()
        for run, st in runs:
            try:
                snapshot.write(run, st)
            except Exception:
                self.log.exception("snapshot of run %s failed at shutdown", run)
            st.wal.close()
        self.log.info("counter %s shut down; %d run(s) saved", self.id, len(runs))

    # ------------------------------------------------------------ ingestion
    def handle(self, tag: str, key: str, payload: bytes) -> None:
        self.queries.step_aside()
        if tag == "status":
            self._take_burst()  # a completed learner's run ends with what came before
            self._on_status(key, payload)
            return
        if tag != "transitions":
            return
        msg = self.decode_for_run(key, payload, Transitions)
        if msg is None:
            return
        st = self.runs.get(msg.run)
        if st is None:
            self.reject(key, f"unknown run: {msg.run}")
            return
        if key.rsplit("/", 1)[-1] != msg.actor:
            why = f"actor mismatch: key and message name different actors ({msg.actor:.64})"
            self._run_reject(st, key, why)
            return
        if not st.cursor.knows(msg.actor) or not is_service_id(msg.actor):
            # not one of the run's actors (the learner refuses its batches too), or
            # (actors not known) an id longer than an id can be, and than the log holds
            self._run_reject(st, key, f"unknown actor: {msg.actor:.64}")
            return
        try:
            check_dims(msg, st.obs_dim, st.act_dim)
            check_batch_rows(msg, st.config.episode_len, st.lockstep)  # the learner's rule
        except WireError as err:
            self._run_reject(st, key, str(err))
            return
        batch = (msg.actor, msg.seq, msg.obs, msg.act)
        if self.pending.add(msg.run, st, batch, time.monotonic()):
            self._take_burst()

    def after_drain(self) -> None:
        self._take_burst()

    def _run_reject(self, st: RunState, key: str, reason: str) -> None:
        with self.runs.lock:
            st.run_rejects += 1
        self.reject(key, reason)

    def _on_status(self, key: str, payload: bytes) -> None:
        """The run's learner completed or failed: publish final stats, snapshot, free."""
        run = run_of(key)
        st = self.runs.get(run) if run else None
        if run is None or st is None or key.rsplit("/", 1)[-1] != st.learner:
            return  # other services' status: not ours to act on
        msg = self.decode_for_run(key, payload, Status)
        if msg is None or msg.state not in ("completed", "failed"):
            return
        self.publish_metrics(run, self._run_stats(st), source="counter")
        self.on_stop(run, f"learner {msg.state}")
        reason = learner_end_reason(msg) if msg.state == "failed" else None
        self.publish_status(run, msg.state, reason=reason, **self._run_stats(st))
        self.free(run)

    def _take_burst(self) -> None:
        """Take every buffered batch: per run one plan (`burst.plan`), one commit, one ack."""
        if not self.pending.runs:
            return
        for run, (st, batches) in self.pending.take().items():
            if not st.closed:  # a run stopped meanwhile has written its last snapshot
                plan = burst.plan(st.cursor, batches)
                burst.commit(st, plan, self.runs.lock, self.queries.step_aside)
                self._ack(run, st)

    def _ack(self, run: str, st: RunState) -> None:
        with self.runs.lock:
            acked = st.cursor.positions()
        attempt = self.served.attempts.get(run)  # (a restored run's: its attempt.json)
        ack = encode(Ack(run, service=self.id, acked=acked, window=0, attempt=attempt))
        self.bus.put(k_ack(run, self.id), ack)

    # ------------------------------------------------------------ bonus queries
    def _on_bonus(self, key: str, payload: bytes) -> bytes | Refused | None:
        """On Zenoh's thread: counts and bonus for B rows, or the reject's reason as a
        refusal (the learner counts it apart from a query nobody answered)."""
        with self.queries.answering():
            t0 = time.perf_counter()
            msg, why = self.decode_or_why(key, payload, BonusQuery)
            if msg is None:
                return Refused(self.id, why or "not a run served here")
            st = self.runs.get(msg.run)
            if st is None:
                self.reject(key, f"unknown run: {msg.run}")
                return Refused(self.id, f"unknown run: {msg.run}")
            if not self.of_attempt(msg.run, msg.attempt):
                # Its tables are another attempt's: a run restored from disk after its
                # attempt ended (no stop reached this counter), whose retry another
                # counter counts, or this one once its start comes.
                held = self.served.attempts.get(msg.run)
                why = f"another attempt: asked for attempt {msg.attempt}, holds {held}"
                self.reject(key, f"bonus query of {why}")
                return Refused(self.id, f"the counter's tables are of {why}")
            try:
                bonus.check(st, msg)
            except WireError as err:
                self._run_reject(st, key, str(err))
                return Refused(self.id, str(err))
            return bonus.answer(st, msg, self.runs.lock, t0, self.id)

    # ------------------------------------------------------------ stats, timers
    def tick(self) -> bool:
        now = time.monotonic()
        if self.pending.due(now):
            self._take_burst()  # an inbox that never empties still gets its acks
        if now >= self._next_stats:
            self._next_stats = now + self.stats_s
            for run, st in self.runs.items():
                update_rate(st, now)
                self.publish_metrics(run, self._run_stats(st), source="counter")
                if st.cursor.positions():
                    self._ack(run, st)  # repeated: a restarted actor or a lost ack catches up
        if now >= self._next_snapshot:
            self._take_burst()  # not kept waiting for their acks while the snapshot runs
            for run, st in self.runs.items():
                if snapshot.due(st):
                    try:
                        snapshot.write(run, st)
                    except OSError:
                        self.log.exception("snapshot of run %s failed (the log keeps it)", run)
            self._next_snapshot = snapshot.next_check(now, self.snapshot_s, time.monotonic() - now)
        return False  # its work comes in messages: nothing waits between them

    def _run_stats(self, st: RunState) -> dict[str, Any]:
        """The run's stats as published (`CounterStats`' map)."""
        _, rejects_total = self.reject_tally.counts()
        with self.runs.lock:
            return run_stats(st, rejects_total).to_wire()

    def info(self) -> CounterInfo:
        base = super().info()
        stats = {}
        for run, st in self.runs.items():
            stats[run] = self._run_stats(st)
            with self.runs.lock:
                stats[run]["acked"] = st.cursor.positions()
            stats[run]["attempt"] = self.served.attempts.get(run)  # (restored: its noted one)
        return CounterInfo(
            **{f.name: getattr(base, f.name) for f in dataclasses.fields(ServiceInfo)},
            run_stats=stats,
            ready=self._ready,
            snapshot_s=self.snapshot_s,
        )


def make_service(service_id: str, connect: list[str], data_dir: Path) -> CounterService:
    # Process-wide, so set here (the counter's own process) rather than in the class; a
    # short interval keeps the ingest thread from holding the GIL while a query waits.
    sys.setswitchinterval(settings().counter_switch_s)  # MACB_COUNTER_SWITCH_S
    return CounterService(service_id, connect, data_dir)
