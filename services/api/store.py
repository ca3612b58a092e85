"""The API's store: experiments, runs and every metric point, in one SQLite file.

`Store` is what the routes, the scheduler and the CLI call. Its parts: `db.py` (the
file: connections, write transactions, the schema and its migrations), `points.py`
(the metric points: idempotent appends, pages as stored JSON, per-run counts); the
experiments and runs tables are read and written here, where a run's life is: queued,
claimed (a group's runs all or none), waiting, finished, stopped with its stop still
to send.

A failed or stopped run can be queued again under its id (`retry_runs`): its points go,
its `attempts` goes up by one, so the record says it ran more than once, and its
`seq_base` keeps their last seq, so the next attempt's points are numbered on from it.
"""

from __future__ import annotations

import json
import sqlite3
import time
from pathlib import Path
from typing import Any

from shared.metrics import ALL_FIELDS
from shared.net.messages import Assignment

from .db import SCHEMA_VERSION, Database, StoreError, default_arm, loads
from .points import Points

__all__ = ["ACTIVE", "CSV_FIELDS", "SCHEMA_VERSION", "STATUSES", "Store", "StoreError"]

CSV_FIELDS = ALL_FIELDS  # the columns of `macb train`, then what the services add

STATUSES = ("queued", "running", "completed", "stopped", "failed")
ACTIVE = ("queued", "running")


class _NotAll(Exception):
    """A group's claim found a run no longer queued (the transaction is rolled back)."""


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
        d[col] = loads(d.get(col), default)
    return d


class Store:
    """Experiments and runs here; points through `Points`; one `Database` under both."""

    def __init__(self, path: str | Path) -> None:
        self.db = Database(path)
        self.path = self.db.path
        self.metrics = Points(self.db)

    def close(self) -> None:
        self.db.close()

    # ------------------------------------------------------------ experiments
    def create_experiment(
        self, exp_id: str, name: str, spec: dict[str, Any], runs: list[dict[str, Any]]
    ) -> None:
        """An experiment and its runs (all queued), in one transaction. Each run is a
        dict of id, seed, arm, point, config and actors."""
        now = time.time()
        with self.db.tx() as c:
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
        row = self.db.conn().execute("SELECT * FROM experiments WHERE id = ?", (exp_id,)).fetchone()
        if row is None:
            return None
        return {**dict(row), "spec": loads(row["spec"], {})}

    def experiments(self, limit: int = 100, offset: int = 0) -> list[dict[str, Any]]:
        rows = self.db.conn().execute(
            "SELECT * FROM experiments ORDER BY created DESC, id DESC LIMIT ? OFFSET ?",
            (limit, offset),
        )
        return [{**dict(r), "spec": loads(r["spec"], {})} for r in rows]

    def count_experiments(self) -> int:
        return self.db.conn().execute("SELECT COUNT(*) FROM experiments").fetchone()[0]

    # ------------------------------------------------------------ runs
    def run(self, run_id: str) -> dict[str, Any] | None:
        row = self.db.conn().execute("SELECT * FROM runs WHERE id = ?", (run_id,)).fetchone()
        return run_row(row) if row else None

    def runs_of(self, exp_ids: list[str]) -> dict[str, list[dict[str, Any]]]:
        out: dict[str, list[dict[str, Any]]] = {e: [] for e in exp_ids}
        if not exp_ids:
            return out
        marks = ",".join("?" * len(exp_ids))
        rows = self.db.conn().execute(
            f"SELECT * FROM runs WHERE experiment_id IN ({marks}) ORDER BY experiment_id, idx",
            exp_ids,
        )
        for r in rows:
            out[r["experiment_id"]].append(run_row(r))
        return out

    def runs_with_status(self, *statuses: str) -> list[dict[str, Any]]:
        marks = ",".join("?" * len(statuses))
        rows = self.db.conn().execute(
            f"SELECT * FROM runs WHERE status IN ({marks}) ORDER BY created, idx", statuses
        )
        return [run_row(r) for r in rows]

    def claim(self, run_id: str, assign: Assignment) -> bool:
        """queued -> running with these services; False if it is no longer queued."""
        return self.claim_all([run_id], assign)

    def claim_all(self, run_ids: list[str], assign: Assignment) -> bool:
        """`claim` for the runs of a group: all of them, or none (one stopped meanwhile, or
        one whose stop is still to go on the bus: a stop and a retry over HTTP after the
        scheduler's stop pass read nothing due; claimed now, the Stop sent next pass,
        which names no attempt, would stop the new one. The next pass claims it.)"""
        marks = ",".join("?" * len(run_ids))
        try:
            with self.db.tx() as c:
                cur = c.execute(
                    "UPDATE runs SET status = 'running', started = ?, assign = ?, reason = NULL"
                    f" WHERE id IN ({marks}) AND status = 'queued' AND stop_sent = 1",
                    (time.time(), json.dumps(assign.to_wire()), *run_ids),
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
        with self.db.tx() as c:
            c.executemany(
                "UPDATE runs SET reason = ? WHERE id = ? AND status = 'queued' AND reason IS NOT ?",
                [(reason, run_id, reason) for run_id, reason in reasons.items()],
            )

    def finish(
        self, run_id: str, status: str, reason: str | None = None, stop_sent: bool | None = True
    ) -> bool:
        """Move an active run to a final status; False (and no change) if it had ended.
        `stop_sent` None: whether it was queued, read in the same statement (a user's
        stop: a run the scheduler started meanwhile still has its services to stop)."""
        assert status in ("completed", "stopped", "failed")
        sent = "status = 'queued'" if stop_sent is None else str(int(stop_sent))
        with self.db.tx() as c:
            cur = c.execute(
                f"UPDATE runs SET status = ?, reason = ?, ended = ?, stop_sent = ({sent})"
                " WHERE id = ? AND status IN ('queued', 'running')",
                (status, reason, time.time(), run_id),
            )
            return cur.rowcount == 1

    def stop_experiment(self, exp_id: str, reason: str) -> list[str]:
        """Stop every active run of an experiment; the ids of the runs stopped."""
        with self.db.tx() as c:
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
        given), under the same ids: their points are deleted (their last seq kept as the
        run's `seq_base`: seq goes on from it), `attempts` goes up, the reason says what
        they were. In one transaction; the runs retried (as they were
        before), [] when there is nothing to retry. A stop not yet sent stays due: the
        scheduler sends it before the run can be started again."""
        with self.db.tx() as c:
            rows = c.execute(
                "SELECT id, status, reason, attempts FROM runs WHERE experiment_id = ?"
                " AND status IN ('failed', 'stopped') ORDER BY idx",
                (exp_id,),
            ).fetchall()
            rows = [r for r in rows if run_ids is None or r["id"] in run_ids]
            for r in rows:
                was = r["status"] + (f": {r['reason']}" if r["reason"] else "")
                reason = f"retried (attempt {r['attempts'] + 1}; was {was})"
                c.execute(
                    "UPDATE runs SET status = 'queued', reason = ?, started = NULL,"
                    " ended = NULL, assign = NULL, services = '{}', live = '{}',"
                    " attempts = attempts + 1, seq_base = COALESCE("
                    "(SELECT MAX(seq) FROM metrics WHERE run_id = runs.id), seq_base)"
                    " WHERE id = ?",
                    (reason, r["id"]),
                )
                c.execute("DELETE FROM metrics WHERE run_id = ?", (r["id"],))
            return [dict(r) for r in rows]

    def stops_to_send(self) -> list[tuple[str, str]]:
        rows = self.db.conn().execute("SELECT id, reason FROM runs WHERE stop_sent = 0").fetchall()
        return [(r["id"], r["reason"] or "stopped") for r in rows]

    def stop_sent(self, run_id: str) -> None:
        with self.db.tx() as c:
            c.execute("UPDATE runs SET stop_sent = 1 WHERE id = ?", (run_id,))

    def set_services(
        self, run_id: str, services: dict[str, Any], attempt: int | None = None
    ) -> None:
        self._set(run_id, "services", json.dumps(services), attempt)

    def set_live(self, run_id: str, live: dict[str, Any], attempt: int | None = None) -> None:
        self._set(run_id, "live", json.dumps(live), attempt)

    def set_reason(self, run_id: str, reason: str | None, attempt: int | None = None) -> None:
        self._set(run_id, "reason", reason, attempt)

    def _set(self, run_id: str, column: str, value: str | None, attempt: int | None) -> None:
        """One column of a run's row; with `attempt`, only while that attempt is the run's
        current one (read in the same statement): what a watch learned of an attempt
        stopped and retried over HTTP, before the scheduler saw it end, must not land on
        the queued run or its next attempt."""
        assert column in ("services", "live", "reason")
        where, args = ("", ()) if attempt is None else (" AND attempts = ?", (attempt,))
        with self.db.tx() as c:
            c.execute(f"UPDATE runs SET {column} = ? WHERE id = ?{where}", (value, run_id, *args))

    # ------------------------------------------------------------ metric points
    def add_points(
        self, run_id: str, rows: list[dict[str, Any]], attempt: int | None = None
    ) -> int:
        return self.metrics.add(run_id, rows, attempt)

    def points_json(
        self, run_id: str, since: int = 0, limit: int = 10_000
    ) -> tuple[str, int, int, int, bool]:
        return self.metrics.page_json(run_id, since, limit)

    def points(self, run_id: str, since: int = 0, limit: int = 1_000_000) -> list[dict[str, Any]]:
        return self.metrics.rows(run_id, since, limit)

    def point_stats(self, run_ids: list[str]) -> dict[str, tuple[int, int, int]]:
        return self.metrics.stats(run_ids)

    def snapshot(self) -> dict[str, list[tuple]]:
        """Every row of every table (tests: check that refused requests changed nothing)."""
        conn = self.db.conn()
        return {
            t: [tuple(r) for r in conn.execute(f"SELECT * FROM {t} ORDER BY 1, 2")]
            for t in ("experiments", "runs", "metrics")
        }
