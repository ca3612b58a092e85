"""The API's store: experiments, runs and every metric point, in one SQLite file.

WAL mode, so readers (HTTP requests) never wait for the writer (the scheduler);
one connection per thread, and one lock that serialises writers. The schema has a
version table; `Store` creates or checks it on open, so a newer file is refused
instead of being misread, and an older one is migrated in place (in one transaction):
schema 2 gave each run its arm's name (`runs.arm`), which schema 1 files get from the
run's grid point and config by the rule new runs are named by.

A metric point is stored as the JSON of the evaluator's row with its `seq` (its
number in the run, from 1, in arrival order) put in front; reads concatenate the
stored JSON as it is, so serving 10,000 points decodes nothing. A point repeated
for the same evaluation episode is ignored: storing is idempotent.

A failed or stopped run can be queued again under its id (`retry_runs`): its points go,
its `attempts` (schema 3) goes up by one, so the record says it ran more than once.
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from shared.metrics import ALL_FIELDS

from .naming import base_name, point_name

SCHEMA_VERSION = 3  # 1: first; 2: runs.arm; 3: runs.attempts

CSV_FIELDS = ALL_FIELDS  # the columns of `macb train`, then what the services add

STATUSES = ("queued", "running", "completed", "stopped", "failed")
ACTIVE = ("queued", "running")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS schema_version (version INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS experiments (
    id          TEXT PRIMARY KEY,
    name        TEXT NOT NULL,
    created     REAL NOT NULL,
    spec        TEXT NOT NULL          -- JSON: base config, seeds, grid, arms, actors
);
CREATE TABLE IF NOT EXISTS runs (
    id            TEXT PRIMARY KEY,
    experiment_id TEXT NOT NULL REFERENCES experiments(id),
    idx           INTEGER NOT NULL,
    seed          INTEGER NOT NULL,
    arm           TEXT NOT NULL DEFAULT '',  -- its arm's name (curves group by it)
    point         TEXT NOT NULL,       -- JSON: keys set over the base ({"beta": .., "k": ..})
    config        TEXT NOT NULL,       -- JSON: the full TrainConfig of the run
    actors        INTEGER NOT NULL,
    status        TEXT NOT NULL CHECK (status IN
                    ('queued', 'running', 'completed', 'stopped', 'failed')),
    reason        TEXT,                -- why it failed or stopped, or what it waits for
    created       REAL NOT NULL,
    started       REAL,
    ended         REAL,
    assign        TEXT,                -- JSON: services serving it (counter, learner, ...)
    services      TEXT NOT NULL DEFAULT '{}',  -- JSON: service id -> last status
    live          TEXT NOT NULL DEFAULT '{}',  -- JSON: source -> latest stats
    stop_sent     INTEGER NOT NULL DEFAULT 1,  -- 0: a stop must still go on the bus
    attempts      INTEGER NOT NULL DEFAULT 1   -- 1 + how often it was queued again
);
CREATE INDEX IF NOT EXISTS runs_by_experiment ON runs(experiment_id, idx);
CREATE INDEX IF NOT EXISTS runs_by_status ON runs(status, created, idx);
CREATE TABLE IF NOT EXISTS metrics (
    run_id   TEXT NOT NULL REFERENCES runs(id),
    seq      INTEGER NOT NULL,
    episode  INTEGER NOT NULL,
    received REAL NOT NULL,
    data     TEXT NOT NULL,            -- JSON object: {"seq": .., row fields ..}
    PRIMARY KEY (run_id, seq),
    UNIQUE (run_id, episode)
);
"""


class _NotAll(Exception):
    """A group's claim found a run no longer queued (the transaction is rolled back)."""


class StoreError(RuntimeError):
    """The store file cannot be used (a newer schema, say)."""


def _loads(text: str | None, default: Any = None) -> Any:
    return json.loads(text) if text else default


def run_row(r: sqlite3.Row) -> dict[str, Any]:
    """A runs row as a plain dict with its JSON columns decoded."""
    d = dict(r)
    for col, default in (
        ("point", {}),
        ("config", {}),
        ("assign", None),
        ("services", {}),
        ("live", {}),
    ):
        d[col] = _loads(d.get(col), default)
    return d


def default_arm(point: dict[str, Any], config: dict[str, Any]) -> str:
    """The arm name of a run that was given none: its grid point's, or its algo and bonus'."""
    return point_name(point) if point else base_name(config)


def _add_arms(c: sqlite3.Connection) -> None:
    """Schema 1 -> 2: a column with each run's arm name, named from its grid point (or,
    without one, its algo and bonus), as the experiment would name it today."""
    c.execute("ALTER TABLE runs ADD COLUMN arm TEXT NOT NULL DEFAULT ''")
    rows = c.execute("SELECT id, point, config FROM runs").fetchall()
    c.executemany(
        "UPDATE runs SET arm = ? WHERE id = ?",
        [(default_arm(_loads(r["point"], {}), _loads(r["config"], {})), r["id"]) for r in rows],
    )


def _add_attempts(c: sqlite3.Connection) -> None:
    """Schema 2 -> 3: every run so far ran (or will run) once."""
    c.execute("ALTER TABLE runs ADD COLUMN attempts INTEGER NOT NULL DEFAULT 1")


class Store:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._local = threading.local()
        self._conns: list[sqlite3.Connection] = []
        self._conns_lock = threading.Lock()
        self._write = threading.Lock()
        self._closed = False
        self._migrate()

    # ------------------------------------------------------------ connections
    def _conn(self) -> sqlite3.Connection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            if self._closed:
                raise StoreError("the store is closed")
            conn = sqlite3.connect(
                self.path, timeout=30, isolation_level=None, check_same_thread=False
            )
            conn.row_factory = sqlite3.Row
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=NORMAL")
            conn.execute("PRAGMA foreign_keys=ON")
            conn.execute("PRAGMA busy_timeout=30000")
            self._local.conn = conn
            with self._conns_lock:
                self._conns.append(conn)
        return conn

    @contextlib.contextmanager
    def tx(self) -> Iterator[sqlite3.Connection]:
        """One write transaction (writers are serialised; readers go on meanwhile)."""
        conn = self._conn()
        with self._write:
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")

    def close(self) -> None:
        self._closed = True
        with self._conns_lock:
            for conn in self._conns:
                with contextlib.suppress(sqlite3.Error):
                    conn.close()
            self._conns.clear()
        self._local = threading.local()

    def _migrate(self) -> None:
        with self.tx() as c:
            for statement in _SCHEMA.split(";"):
                if statement.strip():
                    c.execute(statement)
            row = c.execute("SELECT version FROM schema_version").fetchone()
            if row is None:
                c.execute("INSERT INTO schema_version VALUES (?)", (SCHEMA_VERSION,))
            elif row[0] > SCHEMA_VERSION:
                raise StoreError(
                    f"{self.path} has store schema {row[0]}; this API knows {SCHEMA_VERSION}"
                )
            elif row[0] < SCHEMA_VERSION:
                if row[0] < 2:
                    _add_arms(c)
                if row[0] < 3:
                    _add_attempts(c)
                c.execute("UPDATE schema_version SET version = ?", (SCHEMA_VERSION,))

    # ------------------------------------------------------------ experiments
    def create_experiment(
        self, exp_id: str, name: str, spec: dict[str, Any], runs: list[dict[str, Any]]
    ) -> None:
        """An experiment and its runs (all queued), in one transaction. Each run is a
        dict of id, seed, arm, point, config and actors."""
        now = time.time()
        with self.tx() as c:
            c.execute(
                "INSERT INTO experiments (id, name, created, spec) VALUES (?, ?, ?, ?)",
                (exp_id, name, now, json.dumps(spec)),
            )
            c.executemany(
                "INSERT INTO runs (id, experiment_id, idx, seed, arm, point, config, actors,"
                " status, created) VALUES (?, ?, ?, ?, ?, ?, ?, ?, 'queued', ?)",
                [
                    (
                        r["id"],
                        exp_id,
                        i,
                        r["seed"],
                        r.get("arm") or default_arm(r["point"], r["config"]),
                        json.dumps(r["point"]),
                        json.dumps(r["config"]),
                        r["actors"],
                        now,
                    )
                    for i, r in enumerate(runs)
                ],
            )

    def experiment(self, exp_id: str) -> dict[str, Any] | None:
        row = self._conn().execute("SELECT * FROM experiments WHERE id = ?", (exp_id,)).fetchone()
        if row is None:
            return None
        return {**dict(row), "spec": _loads(row["spec"], {})}

    def experiments(self, limit: int = 100, offset: int = 0) -> list[dict[str, Any]]:
        rows = self._conn().execute(
            "SELECT * FROM experiments ORDER BY created DESC, id DESC LIMIT ? OFFSET ?",
            (limit, offset),
        )
        return [{**dict(r), "spec": _loads(r["spec"], {})} for r in rows]

    def count_experiments(self) -> int:
        return self._conn().execute("SELECT COUNT(*) FROM experiments").fetchone()[0]

    # ------------------------------------------------------------ runs
    def run(self, run_id: str) -> dict[str, Any] | None:
        row = self._conn().execute("SELECT * FROM runs WHERE id = ?", (run_id,)).fetchone()
        return run_row(row) if row else None

    def runs_of(self, exp_ids: list[str]) -> dict[str, list[dict[str, Any]]]:
        out: dict[str, list[dict[str, Any]]] = {e: [] for e in exp_ids}
        if not exp_ids:
            return out
        marks = ",".join("?" * len(exp_ids))
        rows = self._conn().execute(
            f"SELECT * FROM runs WHERE experiment_id IN ({marks}) ORDER BY experiment_id, idx",
            exp_ids,
        )
        for r in rows:
            out[r["experiment_id"]].append(run_row(r))
        return out

    def runs_with_status(self, *statuses: str) -> list[dict[str, Any]]:
        marks = ",".join("?" * len(statuses))
        rows = self._conn().execute(
            f"SELECT * FROM runs WHERE status IN ({marks}) ORDER BY created, idx", statuses
        )
        return [run_row(r) for r in rows]

    def claim(self, run_id: str, assign: dict[str, Any]) -> bool:
        """queued -> running with these services; False if it is no longer queued."""
        return self.claim_all([run_id], assign)

    def claim_all(self, run_ids: list[str], assign: dict[str, Any]) -> bool:
        """`claim` for the runs of a group: all of them, or none (one stopped meanwhile)."""
        marks = ",".join("?" * len(run_ids))
        try:
            with self.tx() as c:
                cur = c.execute(
                    "UPDATE runs SET status = 'running', started = ?, assign = ?, reason = NULL"
                    f" WHERE id IN ({marks}) AND status = 'queued'",
                    (time.time(), json.dumps(assign), *run_ids),
                )
                if cur.rowcount != len(run_ids):
                    raise _NotAll  # rolled back: none is claimed
        except _NotAll:
            return False
        return True

    def set_waiting(self, reasons: dict[str, str]) -> None:
        """Say what queued runs wait for (run id -> reason), in one transaction."""
        if not reasons:
            return
        with self.tx() as c:
            c.executemany(
                "UPDATE runs SET reason = ? WHERE id = ? AND status = 'queued' AND reason IS NOT ?",
                [(reason, run_id, reason) for run_id, reason in reasons.items()],
            )

    def finish(
        self, run_id: str, status: str, reason: str | None = None, stop_sent: bool = True
    ) -> bool:
        """Move an active run to a final status; False (and no change) if it had ended."""
        assert status in ("completed", "stopped", "failed")
        with self.tx() as c:
            cur = c.execute(
                "UPDATE runs SET status = ?, reason = ?, ended = ?, stop_sent = ?"
                " WHERE id = ? AND status IN ('queued', 'running')",
                (status, reason, time.time(), int(stop_sent), run_id),
            )
            return cur.rowcount == 1

    def stop_experiment(self, exp_id: str, reason: str) -> list[str]:
        """Stop every active run of an experiment; the ids of the runs stopped."""
        with self.tx() as c:
            rows = c.execute(
                "SELECT id, status FROM runs WHERE experiment_id = ?"
                " AND status IN ('queued', 'running') ORDER BY idx",
                (exp_id,),
            ).fetchall()
            now = time.time()
            for r in rows:
                c.execute(
                    "UPDATE runs SET status = 'stopped', reason = ?, ended = ?, stop_sent = ?"
                    " WHERE id = ?",
                    (reason, now, int(r["status"] == "queued"), r["id"]),
                )
            return [r["id"] for r in rows]

    def retry_runs(self, exp_id: str, run_ids: list[str] | None = None) -> list[dict[str, Any]]:
        """Queue the experiment's failed and stopped runs again (of `run_ids` only, if
        given), under the same ids: their points are deleted, `attempts` goes up, the
        reason says what they were. In one transaction; the runs retried (as they were
        before), [] when there is nothing to retry. A stop not yet sent stays due: the
        scheduler sends it before the run can be started again."""
        with self.tx() as c:
            rows = c.execute(
                "SELECT id, status, reason, attempts FROM runs WHERE experiment_id = ?"
                " AND status IN ('failed', 'stopped') ORDER BY idx",
                (exp_id,),
            ).fetchall()
            rows = [r for r in rows if run_ids is None or r["id"] in run_ids]
            for r in rows:
                was = r["status"] + (f": {r['reason']}" if r["reason"] else "")
                reason = f"retried (attempt {r['attempts'] + 1}; was {was})"
                c.execute("DELETE FROM metrics WHERE run_id = ?", (r["id"],))
                c.execute(
                    "UPDATE runs SET status = 'queued', reason = ?, started = NULL,"
                    " ended = NULL, assign = NULL, services = '{}', live = '{}',"
                    " attempts = attempts + 1 WHERE id = ?",
                    (reason, r["id"]),
                )
            return [dict(r) for r in rows]

    def stops_to_send(self) -> list[tuple[str, str]]:
        rows = self._conn().execute("SELECT id, reason FROM runs WHERE stop_sent = 0").fetchall()
        return [(r["id"], r["reason"] or "stopped") for r in rows]

    def stop_sent(self, run_id: str) -> None:
        with self.tx() as c:
            c.execute("UPDATE runs SET stop_sent = 1 WHERE id = ?", (run_id,))

    def set_services(self, run_id: str, services: dict[str, Any]) -> None:
        with self.tx() as c:
            c.execute("UPDATE runs SET services = ? WHERE id = ?", (json.dumps(services), run_id))

    def set_live(self, run_id: str, live: dict[str, Any]) -> None:
        with self.tx() as c:
            c.execute("UPDATE runs SET live = ? WHERE id = ?", (json.dumps(live), run_id))

    def set_reason(self, run_id: str, reason: str | None) -> None:
        with self.tx() as c:
            c.execute("UPDATE runs SET reason = ? WHERE id = ?", (reason, run_id))

    # ------------------------------------------------------------ metrics
    def add_points(self, run_id: str, rows: list[dict[str, Any]]) -> int:
        """Append metric rows (one per evaluation episode); the number newly stored."""
        if not rows:
            return 0
        added = 0
        now = time.time()
        with self.tx() as c:
            seq = c.execute(
                "SELECT COALESCE(MAX(seq), 0) FROM metrics WHERE run_id = ?", (run_id,)
            ).fetchone()[0]
            for row in rows:
                episode = int(row["episode"])
                data = json.dumps({"seq": seq + 1, **{k: v for k, v in row.items() if k != "seq"}})
                cur = c.execute(
                    "INSERT OR IGNORE INTO metrics (run_id, seq, episode, received, data)"
                    " VALUES (?, ?, ?, ?, ?)",
                    (run_id, seq + 1, episode, now, data),
                )
                if cur.rowcount == 1:
                    seq += 1
                    added += 1
        return added

    def points_json(self, run_id: str, since: int = 0, limit: int = 10_000) -> tuple[str, int, int]:
        """Points after `since` as a JSON array text; (text, count, last seq)."""
        rows = (
            self._conn()
            .execute(
                "SELECT seq, data FROM metrics WHERE run_id = ? AND seq > ? ORDER BY seq LIMIT ?",
                (run_id, since, limit),
            )
            .fetchall()
        )
        last = rows[-1][0] if rows else since
        return "[" + ",".join(r[1] for r in rows) + "]", len(rows), last

    def points(self, run_id: str, since: int = 0, limit: int = 1_000_000) -> list[dict[str, Any]]:
        rows = self._conn().execute(
            "SELECT data FROM metrics WHERE run_id = ? AND seq > ? ORDER BY seq LIMIT ?",
            (run_id, since, limit),
        )
        return [json.loads(r[0]) for r in rows]

    def point_stats(self, run_ids: list[str]) -> dict[str, tuple[int, int, int]]:
        """run -> (number of points, last seq, last episode).

        seq runs 1, 2, ... without holes, so the count is the last seq: two index
        look-ups per run, whatever the number of points."""
        if not run_ids:
            return {}
        marks = ",".join("?" * len(run_ids))
        rows = self._conn().execute(
            "SELECT r.id,"
            " (SELECT MAX(seq) FROM metrics m WHERE m.run_id = r.id),"
            " (SELECT MAX(episode) FROM metrics m WHERE m.run_id = r.id)"
            f" FROM runs r WHERE r.id IN ({marks})",
            run_ids,
        )
        out = {r: (0, 0, 0) for r in run_ids}
        for run_id, last_seq, last_episode in rows:
            out[run_id] = (last_seq or 0, last_seq or 0, last_episode or 0)
        return out

    def has_more(self, run_id: str, since: int) -> bool:
        row = (
            self._conn()
            .execute("SELECT 1 FROM metrics WHERE run_id = ? AND seq > ? LIMIT 1", (run_id, since))
            .fetchone()
        )
        return row is not None

    def snapshot(self) -> dict[str, list[tuple]]:
        """Every row of every table (tests: check that refused requests changed nothing)."""
        conn = self._conn()
        return {
            t: [tuple(r) for r in conn.execute(f"SELECT * FROM {t} ORDER BY 1, 2")]
            for t in ("experiments", "runs", "metrics")
        }
