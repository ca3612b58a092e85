"""A run's metric points: the `metrics` table, written by the scheduler, read by HTTP.

A point is stored as the JSON of the evaluator's row with its `seq` (its number in the
run, in arrival order) put in front; reads concatenate the stored JSON as it is, so
serving many points decodes nothing. A point repeated for the same evaluation episode
is ignored, so storing is idempotent (rows come at least once); rows of an attempt
other than the run's current one are not stored.

A run's seq never goes back: a retry deletes the points but keeps their last seq as the
run's `seq_base`, and the next attempt's points are numbered on from it. So a cursor
(`since`, Last-Event-ID) taken in an earlier attempt reads every point of the new one.
An attempt's seqs have no holes, so a run's count is its last seq less its base: two
index look-ups per run.
"""

from __future__ import annotations

import json
import time
from typing import Any

from .db import Database

STATS_SLICE = 900  # run ids bound in one `stats` query (under any SQLite's limit)


class Points:
    """The metric points of every run, over the store's `Database`."""

    def __init__(self, db: Database) -> None:
        self.db = db

    def add(self, run_id: str, rows: list[dict[str, Any]], attempt: int | None = None) -> int:
        """Append metric rows (one per evaluation episode); the number newly stored.

        `attempt`: the run's attempt the rows are of (None: whichever is current). They
        are stored only while it is the run's current attempt, read in this transaction:
        a retry may have queued the run again since they were sent, and an ended
        attempt's row would take the episode from the new attempt's own row."""
        if not rows:
            return 0
        added = 0
        now = time.time()
        with self.db.tx() as c:
            run = c.execute(
                "SELECT r.attempts, COALESCE((SELECT MAX(seq) FROM metrics WHERE run_id = r.id),"
                " r.seq_base) FROM runs r WHERE r.id = ?",
                (run_id,),
            ).fetchone()
            if run is None or (attempt is not None and run[0] != attempt):
                return 0
            seq = run[1]
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

    def page_json(
        self, run_id: str, since: int = 0, limit: int = 10_000
    ) -> tuple[str, int, int, int, bool]:
        """Points after `since` as a JSON array text: (text, count, last seq, attempt,
        more), read in one statement, so that `attempt` (the run's current one) is the
        attempt of every point in the page (a retry deletes the earlier attempts' points
        in the transaction that counts the new one) and `more` (points remain after
        these) is of the same state. An empty page reads the attempt alone; 0 for an
        unknown run."""
        conn = self.db.conn()
        rows = conn.execute(
            "SELECT (SELECT attempts FROM runs WHERE id = ?), seq, data FROM metrics"
            " WHERE run_id = ? AND seq > ? ORDER BY seq LIMIT ?",
            (run_id, run_id, since, limit + 1),
        ).fetchall()
        more = len(rows) > limit
        rows = rows[:limit]
        if rows:
            attempt, last = rows[0][0], rows[-1][1]
        else:
            got = conn.execute("SELECT attempts FROM runs WHERE id = ?", (run_id,)).fetchone()
            attempt, last = (got[0] if got else 0), since
        return "[" + ",".join(r[2] for r in rows) + "]", len(rows), last, attempt, more

    def rows(self, run_id: str, since: int = 0, limit: int = 1_000_000) -> list[dict[str, Any]]:
        """Points after `since`, decoded, in seq order."""
        rows = self.db.conn().execute(
            "SELECT data FROM metrics WHERE run_id = ? AND seq > ? ORDER BY seq LIMIT ?",
            (run_id, since, limit),
        )
        return [json.loads(r[0]) for r in rows]

    def stats(self, run_ids: list[str]) -> dict[str, tuple[int, int, int]]:
        """run -> (number of points, last seq, last episode); (0, 0, 0) for none (a
        retried run's before its new attempt's first point)."""
        out = {r: (0, 0, 0) for r in run_ids}
        # In slices: SQLite binds at most 32,766 variables (999 before 3.32), and a page
        # of experiments may hold more runs than that.
        for i in range(0, len(run_ids), STATS_SLICE):
            part = run_ids[i : i + STATS_SLICE]
            rows = self.db.conn().execute(
                "SELECT r.id, r.seq_base,"
                " (SELECT MAX(seq) FROM metrics m WHERE m.run_id = r.id),"
                " (SELECT MAX(episode) FROM metrics m WHERE m.run_id = r.id)"
                f" FROM runs r WHERE r.id IN ({','.join('?' * len(part))})",
                part,
            )
            for run_id, base, last_seq, last_episode in rows:
                if last_seq is not None:
                    out[run_id] = (last_seq - base, last_seq, last_episode)
        return out
