"""The counter service: the count tables of every active run, exactly once per transition.

It owns the tables because counts must change only on collection, once per transition,
whoever else sees the transitions: every run's batches are taken by the receive rule of
`shared.net.protocol.ReceiveCursor` (duplicates ignored, an overlap's new tail taken, gaps
dropped for the actor to resend), hashed in bursts, written to a write-ahead log and
only then counted and acknowledged, so an acknowledged count survives a SIGKILL.
Bonus queries are answered on Zenoh's thread under the lock ingestion takes, so a
query sees a burst counted whole or not at all, and they come first (a short GIL
switch interval, the service thread stepping aside): the learner waits for them.

Durability (files, snapshot schedule, restore) is in docs/architecture.md, "The
counter's files"; why the burst sizes, switch interval and snapshot spacing are what
they are is in docs/performance.md, "Counter service".
"""

from __future__ import annotations

import os
import queue
import re
import shutil
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from services.common import ServiceBase, learner_end_reason
from services.counter import burst, snapshot
from services.counter.state import RunState
from shared.config import TrainConfig, make_config
from shared.envs.tasks import task_spec_for
from shared.net.bus import k_ack, k_bonus, k_status, k_transitions, run_of
from shared.net.messages import Ack, BonusQuery, BonusReply, Status, Transitions
from shared.net.wire import WireError, check_dims, encode
from shared.persist.files import read_json, write_json
from shared.persist.wal import WriteAheadLog
from shared.run.factories import build_exploration

DEFAULT_SNAPSHOT_S = 5.0
# A timed snapshot rewrites the whole table (0.5 s for 1M keys at k=512) and exists to
# bound what a restart replays: so it waits until the log is this share of its size.
SNAPSHOT_LOG_RATIO = 0.25
# ... and, when the log grows that fast anyway (a flood of new keys), the next check
# waits this many times as long as the last snapshots took: at most ~5% of the time.
SNAPSHOT_SPACING = 20.0
STATS_S = 1.0
# Taken batches wait in a burst until the inbox is empty, this many rows are buffered,
# or the oldest has waited this long: whichever comes first ends the burst.
BURST_MAX_ROWS = 512
BURST_MAX_WAIT_S = 0.002
# The interpreter's default (5 ms) lets the ingest thread hold the GIL for a whole
# slice while a bonus query waits on Zenoh's thread; MACB_COUNTER_SWITCH_S overrides.
DEFAULT_SWITCH_INTERVAL_S = 0.0005
# The longest the service thread steps aside for one bonus query being answered.
QUERY_YIELD_MAX_S = 0.005
_RUN_ID = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._-]{0,127}")


class CounterService(ServiceBase):
    role = "counter"
    inbox_type = queue.SimpleQueue  # thousands of batches a second go through it
    max_runs = 1_000_000  # it owns the tables of every active run
    rejoins = False  # it restores every unfinished run from its own files (_restore_all)

    def __init__(
        self,
        service_id: str,
        connect: list[str] | None,
        data_dir: Path,
        snapshot_s: float | None = None,
        stats_s: float = STATS_S,
    ) -> None:
        # Set before the base class declares the info queryable (it calls info()).
        self._lock = threading.RLock()  # tables and run states: ingestion vs queries/info
        self._reject_lock = threading.Lock()
        self._runs: dict[str, RunState] = {}
        self._restored: set[str] = set()  # runs resumed from disk, not started here
        self._ready = False
        # Validated batches not yet taken: (run, state, actor, seq, obs, act), in order.
        self._burst: list[tuple[str, RunState, str, int, np.ndarray, np.ndarray]] = []
        self._burst_rows = 0
        self._burst_t = 0.0  # when the oldest batch of the burst arrived
        # Bonus queries being answered now (on Zenoh's threads); the service thread steps
        # aside while there are any (`_yield_to_queries`).
        self._queries_lock = threading.Lock()
        self._queries_now = 0
        self._no_queries = threading.Event()
        self._no_queries.set()
        if snapshot_s is None:
            snapshot_s = float(os.environ.get("MACB_COUNTER_SNAPSHOT_S", DEFAULT_SNAPSHOT_S))
        self.snapshot_s = snapshot_s
        self.stats_s = stats_s
        super().__init__(service_id, connect, data_dir)
        self.root = self.data_dir / "counter"
        self.root.mkdir(parents=True, exist_ok=True)
        # Subscribe before restoring: batches arriving meanwhile wait in the inbox.
        self.listen(k_transitions("*", "*"), "transitions")
        self.listen(k_status("*", "*"), "status")
        self._restore_all()
        self.bus.queryable(k_bonus("*"), self._on_bonus)
        now = time.monotonic()
        self._next_stats = now + self.stats_s
        self._next_snapshot = now + self.snapshot_s
        self._ready = True
        self.log.info("counter %s ready (data in %s)", self.id, self.root)

    # ------------------------------------------------------------ run lifecycle
    def on_start(self, run: str, config: TrainConfig, assign: dict[str, Any]) -> None:
        if not _RUN_ID.fullmatch(run):
            raise ValueError(f"run id {run!r} is not a safe directory name")
        path = self.root / run
        if path.exists():
            saved = read_json(path / "config.json")
            if (path / "stopped").exists() or saved != config.model_dump(mode="json"):
                why = "was stopped" if (path / "stopped").exists() else "had another config"
                dest = self._archive(path)
                self.log.warning("run %s %s: old state moved to %s", run, why, dest)
        path.mkdir(parents=True, exist_ok=True)
        write_json(path / "config.json", config.model_dump(mode="json"))
        write_json(path / "assign.json", assign)
        st, replayed = self._open_run(run, config, path)
        if replayed or st.counted:
            self.log.info(
                "resumed run %s: %d counted, %d keys, %d WAL records replayed",
                run,
                st.counted,
                sum(len(t) for t in st.explorer.tables),
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

    def start_replaces(self, run: str) -> bool:
        """A start for a run resumed from disk at startup: the run was queued again (its
        earlier attempt ended while this counter was down, so no stop reached it). Its
        old tables and expected numbers must not meet the new attempt's transitions,
        numbered from 0 again: stop the old state (archived by on_start) and start anew.
        A run started in this process ignores a repeated start as every service does."""
        if run not in self._restored:
            return False
        self.log.warning("run %s: started again while restored from disk: a new attempt", run)
        self.on_stop(run, "a new attempt of the run started")
        self.free(run)
        return True

    def on_stop(self, run: str, reason: str) -> None:
        st = self._runs.get(run)
        if st is None:
            return
        self._take_burst()  # what arrived before the stop is in the final snapshot
        snapshot.write(run, st)
        write_json(st.path / "stopped", {"reason": reason, "time": time.time()})
        self.log.info(
            "stopped run %s (%s): %d counted, %d keys",
            run,
            reason,
            st.counted,
            sum(len(t) for t in st.explorer.tables),
        )

    def free(self, run: str) -> None:
        self._restored.discard(run)
        with self._lock:
            st = self._runs.pop(run, None)
            if st is not None:
                st.closed = True
        if st is not None:
            st.wal.close()
        super().free(run)

    def on_shutdown(self) -> None:
        self._take_burst()
        for run, st in list(self._runs.items()):
            try:
                snapshot.write(run, st)
            except Exception:
                self.log.exception("snapshot of run %s failed at shutdown", run)
            st.wal.close()
        self.log.info("counter %s shut down; %d run(s) saved", self.id, len(self._runs))

    def _open_run(self, run: str, config: TrainConfig, path: Path) -> tuple[RunState, int]:
        """Build the run's tables, load its snapshot and log; register it. Returns replayed."""
        spec = task_spec_for(config)
        explorer = build_exploration(config, spec)
        wal, records = WriteAheadLog.open(path / "wal.bin")
        st = RunState(
            config=config,
            explorer=explorer,
            obs_dim=spec.joint_obs_dim,
            act_dim=spec.joint_act_dim,
            path=path,
            wal=wal,
        )
        try:
            if (path / "snapshot.npz").exists():
                snapshot.load(st)
            replayed = snapshot.replay(run, st, records, self.log)
        except Exception:
            wal.close()
            raise
        st.rate_counted = st.counted
        if (path / "assign.json").exists():
            st.learner = (read_json(path / "assign.json") or {}).get("learner")
        with self._lock:
            self._runs[run] = st
        if replayed:
            snapshot.write(run, st)  # fold the log into a snapshot right away
        return st, replayed

    def _restore_all(self) -> None:
        """Resume every run this counter had not finished (no `stopped` marker)."""
        for path in sorted(self.root.iterdir()):
            if not path.is_dir() or path.name.startswith(".") or (path / "stopped").exists():
                continue
            if not (path / "config.json").exists():
                continue
            run = path.name
            try:
                config = make_config(read_json(path / "config.json"))
                self.active[run] = config
                st, replayed = self._open_run(run, config, path)
                self._restored.add(run)
            except Exception:
                self.log.exception("could not restore run %s from %s", run, path)
                self.active.pop(run, None)
                continue
            self.log.info(
                "restored run %s: %d counted, %d keys, %d WAL records replayed",
                run,
                st.counted,
                sum(len(t) for t in st.explorer.tables),
                replayed,
            )
            self.publish_status(run, "running", restored=True, counted=st.counted)
            self._ack(run, st)

    def _archive(self, path: Path) -> Path:
        archive = self.root / ".archive"
        archive.mkdir(exist_ok=True)
        dest = archive / f"{path.name}.{time.strftime('%Y%m%d-%H%M%S')}.{time.time_ns()}"
        shutil.move(str(path), str(dest))
        return dest

    # ------------------------------------------------------------ snapshots
    # ------------------------------------------------------------ ingestion
    def handle(self, tag: str, key: str, payload: bytes) -> None:
        self._yield_to_queries()
        if tag == "status":
            self._take_burst()  # a completed learner's run ends with what came before
            self._on_status(key, payload)
            return
        if tag != "transitions":
            return
        msg = self.decode_for_run(key, payload, Transitions)
        if msg is None:
            return
        run = msg.run
        st = self._runs.get(run)
        if st is None:
            self.reject(key, f"unknown run: {run}")
            return
        actor = msg.actor
        if key.rsplit("/", 1)[-1] != actor:
            with self._lock:
                st.run_rejects += 1
            self.reject(key, f"actor mismatch: key and message name different actors ({actor})")
            return
        try:
            check_dims(msg, st.obs_dim, st.act_dim)
        except WireError as err:
            with self._lock:
                st.run_rejects += 1
            self.reject(key, str(err))
            return
        if not self._burst:
            self._burst_t = time.monotonic()
        self._burst.append((run, st, actor, msg.seq, msg.obs, msg.act))
        self._burst_rows += len(msg.obs)
        if self._burst_rows >= BURST_MAX_ROWS:
            self._take_burst()

    def after_drain(self) -> None:
        self._take_burst()

    def _on_status(self, key: str, payload: bytes) -> None:
        """The run's learner completed or failed: publish final stats, snapshot, free."""
        run = run_of(key)
        st = self._runs.get(run) if run else None
        if st is None or st.learner is None or key.rsplit("/", 1)[-1] != st.learner:
            return  # other services' status: not ours to act on
        msg = self.decode_for_run(key, payload, Status)
        if msg is None or msg.state not in ("completed", "failed"):
            return
        self.publish_metrics(run, self._run_stats(st), source="counter")
        self.on_stop(run, f"learner {msg.state}")
        detail = self._run_stats(st)
        if msg.state == "failed":
            detail["reason"] = learner_end_reason(msg)
        self.publish_status(run, msg.state, **detail)
        self.free(run)

    def _take_burst(self) -> None:
        """Take every buffered batch: per run one hash, one log write, one ack.

        Per-batch costs (the hash call, a log write, a table lock, above all an ack
        encoded and put on the bus) dominate small batches, so a burst of them, as a
        flood of 20-row episodes arrives, shares one of each.
        """
        if not self._burst:
            return
        burst, self._burst, self._burst_rows = self._burst, [], 0
        by_run: dict[str, tuple[RunState, list[tuple[str, int, np.ndarray, np.ndarray]]]] = {}
        for run, st, actor, seq, obs, act in burst:
            by_run.setdefault(run, (st, []))[1].append((actor, seq, obs, act))
        for run, (st, batches) in by_run.items():
            if not st.closed:  # a run stopped meanwhile has written its last snapshot
                self._ingest(run, st, batches)

    def _ingest(self, run: str, st: RunState, batches: list[burst.Batch]) -> None:
        """Take a burst by the exactly-once rule (`burst.plan`); then hash, log, count
        and acknowledge what was taken, the staged cursor swapped in only once the
        rows are logged."""
        plan = burst.plan(st.cursor, batches)
        if plan.obs is None or plan.act is None:
            with self._lock:
                st.cursor = plan.staged  # only the duplicate/gap tallies changed
        else:
            self._yield_to_queries()
            keys = st.explorer.keys(plan.obs, plan.act)  # no lock: hashers are read-only
            self._yield_to_queries()
            records, pos = [], 0
            for actor, start, rows in plan.segments:
                records.append((actor, start, rows, [k[pos : pos + rows] for k in keys]))
                pos += rows
            st.wal.append_many(records)  # logged before counted and acked
            self._yield_to_queries()
            with self._lock:
                for table, k in zip(st.explorer.tables, keys):
                    table.increment(k)
                st.cursor = plan.staged
                st.counted += pos
            st.dirty = True
        self._ack(run, st)

    def _ack(self, run: str, st: RunState) -> None:
        with self._lock:
            acked = st.cursor.positions()
        ack = encode(Ack(run, service=self.id, acked=acked, window=0))
        self.bus.put(k_ack(run, self.id), ack)

    # ------------------------------------------------------------ bonus queries
    def _on_bonus(self, key: str, payload: bytes) -> bytes | None:
        """On Zenoh's thread: counts and bonus for B rows, or None (rejected, no reply)."""
        with self._queries_lock:
            self._queries_now += 1
            self._no_queries.clear()
        try:
            return self._answer_bonus(key, payload)
        finally:
            with self._queries_lock:
                self._queries_now -= 1
                if not self._queries_now:
                    self._no_queries.set()

    def _yield_to_queries(self) -> None:
        """Wait (at most QUERY_YIELD_MAX_S) while a bonus query is being answered.

        Called by the service thread between messages and between the steps of a
        burst. Whenever the query's thread gives up the GIL (a matrix product, a forced
        switch), the busy service thread would take it and keep it for a whole switch
        interval, and on a loaded machine each such handoff also waits for the OS to
        wake the query's thread: stepping aside shortens the handler's tail under a flood
        (docs/performance.md, "Counter service").
        """
        if not self._no_queries.is_set():
            self._no_queries.wait(QUERY_YIELD_MAX_S)

    def _answer_bonus(self, key: str, payload: bytes) -> bytes | None:
        t0 = time.perf_counter()
        msg = self.decode_for_run(key, payload, BonusQuery)
        if msg is None:
            return None
        run = msg.run
        with self._lock:
            st = self._runs.get(run)
        if st is None:
            self.reject(key, f"unknown run: {run}")
            return None
        obs, act = msg.obs, msg.act
        if obs.ndim != 2 or act.ndim != 2 or len(obs) != len(act):
            with self._lock:
                st.run_rejects += 1
            self.reject(key, "bonus_query: obs and act must be (B, dim) with the same B")
            return None
        try:
            check_dims(msg, st.obs_dim, st.act_dim)
        except WireError as err:
            with self._lock:
                st.run_rejects += 1
            self.reject(key, str(err))
            return None
        batch = len(obs)
        keys = st.explorer.keys(obs, act)
        with self._lock:
            if st.closed:
                return None
            counts = [t.counts(k) for t, k in zip(st.explorer.tables, keys)]
        if counts:
            counts_arr = np.stack(counts).astype(np.int64)
            uncounted = int(np.sum(np.any(counts_arr < 1, axis=0)))
        else:
            counts_arr = np.zeros((0, batch), np.int64)
            uncounted = 0
        bonus = st.explorer.bonus_from_counts([np.maximum(c, 1) for c in counts], batch)
        with self._lock:
            tables = st.explorer.stats()  # O(1): kept up to date as keys are counted
        reply = encode(
            BonusReply(run, counts=counts_arr, bonus=bonus.astype(np.float32), tables=tables)
        )
        elapsed = time.perf_counter() - t0
        with self._lock:
            st.latencies.append(elapsed)
            st.queries += 1
            st.uncounted_rows_queried += uncounted
        return reply

    # ------------------------------------------------------------ stats, timers
    def tick(self) -> None:
        now = time.monotonic()
        if self._burst and now - self._burst_t >= BURST_MAX_WAIT_S:
            self._take_burst()  # an inbox that never empties still gets its acks
        if now >= self._next_stats:
            self._next_stats = now + self.stats_s
            for run, st in list(self._runs.items()):
                dt = now - st.rate_t
                if dt > 0:
                    st.rate = (st.counted - st.rate_counted) / dt
                st.rate_t, st.rate_counted = now, st.counted
                self.publish_metrics(run, self._run_stats(st), source="counter")
                if st.cursor.positions():
                    self._ack(run, st)  # repeated: a restarted actor or a lost ack catches up
        if now >= self._next_snapshot:
            self._take_burst()  # not kept waiting for their acks while the snapshot runs
            for run, st in list(self._runs.items()):
                if st.dirty and st.wal.bytes >= SNAPSHOT_LOG_RATIO * snapshot.size(st):
                    try:
                        snapshot.write(run, st)
                    except OSError:
                        self.log.exception("snapshot of run %s failed (the log keeps it)", run)
            spent = time.monotonic() - now
            self._next_snapshot = now + max(self.snapshot_s, SNAPSHOT_SPACING * spent)

    def _run_stats(self, st: RunState) -> dict[str, Any]:
        with self._lock:
            lat = np.asarray(st.latencies, dtype=np.float64) * 1000.0
            base = st.explorer.stats()
            memory = sum(t.memory_bytes() for t in st.explorer.tables)
            data = {
                "table_size": int(base["table_size"]),
                "count1_pct": float(base["count1_pct"]),
                "counted_transitions": st.counted,
                "duplicates": st.cursor.duplicate_rows,
                "gaps": st.cursor.gaps,
                "rejects_total": self._rejects_total(),
                "run_rejects": st.run_rejects,
                "memory_bytes": int(memory),
                "transitions_per_sec": round(st.rate, 3),
                "query_p50_ms": float(np.percentile(lat, 50)) if lat.size else 0.0,
                "query_p99_ms": float(np.percentile(lat, 99)) if lat.size else 0.0,
                "queries": st.queries,
                "uncounted_rows_queried": st.uncounted_rows_queried,
                "wal_records": st.wal.records,
                "snapshots": st.snapshots,
                "actors": len(st.cursor.positions()),
            }
        return data

    def _rejects_total(self) -> int:
        with self._reject_lock:
            return sum(self.rejects.values())

    def reject(self, key: str, reason: str) -> None:
        with self._reject_lock:  # called from the service thread and Zenoh's
            super().reject(key, reason)

    def info(self) -> dict[str, Any]:
        with self._reject_lock:
            out = super().info()
        with self._lock:
            runs = list(self._runs.items())
        stats = {}
        for run, st in runs:
            stats[run] = self._run_stats(st)
            with self._lock:
                stats[run]["acked"] = st.cursor.positions()
        out["runs"] = stats
        out["ready"] = self._ready
        out["snapshot_s"] = self.snapshot_s
        return out


def make_service(service_id: str, connect: list[str], data_dir: Path) -> CounterService:
    # Process-wide, so set here (the counter's own process) rather than in the class.
    sys.setswitchinterval(float(os.environ.get("MACB_COUNTER_SWITCH_S", DEFAULT_SWITCH_INTERVAL_S)))
    return CounterService(service_id, connect, data_dir)
