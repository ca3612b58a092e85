"""The store's SQLite file: its connections, its write transactions, its schema.

WAL mode, so readers (HTTP requests) never wait for the writer (the scheduler); one
connection per thread, and one lock that serialises writers. The schema has a version
table, created or checked on open, so a newer file is refused instead of being misread
and an older one is migrated in place (in one transaction): schema 2 gave each run its
arm's name (`runs.arm`), which schema 1 files get from the run's grid point and config
by the rule new runs are named by; schema 3 counts a run's attempts; schema 4 keeps the
last seq of a run's earlier attempts (`runs.seq_base`), so a retried run's points are
numbered on from there and a client's cursor (`since`) never meets a seq twice.

The tables' rows are read and written by `store.py` (experiments, runs) and
`points.py` (metric points), both over one `Database`.
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from .naming import base_name, point_name

SCHEMA_VERSION = 4  # 1: first; 2: runs.arm; 3: runs.attempts; 4: runs.seq_base

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
    attempts      INTEGER NOT NULL DEFAULT 1,  -- 1 + how often it was queued again
    seq_base      INTEGER NOT NULL DEFAULT 0   -- the last seq its earlier attempts gave
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


class StoreError(RuntimeError):
    """The store file cannot be used (a newer schema, say)."""


def loads(text: str | None, default: Any = None) -> Any:
    """A JSON column's value; `default` for NULL or empty."""
    return json.loads(text) if text else default


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
        [(default_arm(loads(r["point"], {}), loads(r["config"], {})), r["id"]) for r in rows],
    )


def _add_attempts(c: sqlite3.Connection) -> None:
    """Schema 2 -> 3: every run so far ran (or will run) once."""
    c.execute("ALTER TABLE runs ADD COLUMN attempts INTEGER NOT NULL DEFAULT 1")


def _add_seq_base(c: sqlite3.Connection) -> None:
    """Schema 3 -> 4: numbering starts at 0 for every run. A run retried before holds
    its current attempt's points only, numbered from 1 (the cursors of its earlier
    attempts are lost with them, as they were)."""
    c.execute("ALTER TABLE runs ADD COLUMN seq_base INTEGER NOT NULL DEFAULT 0")


class Database:
    """One SQLite file: a connection per thread, serialised write transactions, and the
    schema created, checked or migrated when it is opened."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._local = threading.local()
        self._conns: list[sqlite3.Connection] = []
        self._conns_lock = threading.Lock()
        self._write = threading.Lock()
        self._closed = False
        self._migrate()

    def conn(self) -> sqlite3.Connection:
        """This thread's connection (opened on first use)."""
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
        conn = self.conn()
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
                if row[0] < 4:
                    _add_seq_base(c)
                c.execute("UPDATE schema_version SET version = ?", (SCHEMA_VERSION,))
