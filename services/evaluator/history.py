"""The rows an evaluator published for its recent runs, kept to answer history queries.

A watcher that was away (the API restarting, say) asks `macb/run/{run}/history/eval`
and fills its gaps instead of losing the points published meanwhile; a point the
learner sends again after its row was lost is answered with the row kept here. Queries
come on Zenoh's thread, rows on the service's, hence the lock.
"""

from __future__ import annotations

import collections
import threading
from typing import Any

HISTORY_RUNS = 64  # runs whose rows are kept for history queries

Row = dict[str, Any]


class RowHistory:
    """Per run, its state and the rows published, for the last `keep` runs, and the
    attempt of the run they are of (a reader of a retried run's next attempt tells an
    ended attempt's rows apart by it, after the service let the run go)."""

    def __init__(self, keep: int = HISTORY_RUNS) -> None:
        self.keep = keep
        # run -> (state, rows, the attempt they are of)
        self._runs: collections.OrderedDict[str, tuple[str, list[Row], int | None]] = (
            collections.OrderedDict()
        )
        self._lock = threading.Lock()

    def start(self, run: str, attempt: int | None = None) -> None:
        """A run begins (as its `attempt`): a run queued again starts afresh, not with
        the old rows."""
        with self._lock:
            self._runs.pop(run, None)
            self._runs[run] = ("running", [], attempt)
            self._trim()

    def answer(self, run: str) -> tuple[str, list[Row], int | None] | None:
        """The run's state, a copy of its rows and their attempt, read at one moment (a
        query comes on Zenoh's thread while a retry's start may reset the run)."""
        with self._lock:
            entry = self._runs.get(run)
            return None if entry is None else (entry[0], list(entry[1]), entry[2])

    def remember(self, run: str, state: str, row: Row | None = None) -> None:
        """The run's state now, and a row it published; the run becomes the newest kept."""
        with self._lock:
            _, rows, attempt = self._runs.pop(run, ("running", [], None))
            if row is not None:
                rows.append(row)
            self._runs[run] = (state, rows, attempt)
            self._trim()

    def _trim(self) -> None:
        while len(self._runs) > self.keep:
            self._runs.popitem(last=False)

    def get(self, run: str) -> tuple[str, list[Row]] | None:
        """The run's state and a copy of its rows; None if it is not kept here."""
        with self._lock:
            entry = self._runs.get(run)
            return None if entry is None else (entry[0], list(entry[1]))

    def row(self, run: str, point: int) -> Row | None:
        """The row published for evaluation point `point` of `run`, if kept."""
        entry = self.get(run)
        return next((r for r in entry[1] if r["episode"] == point), None) if entry else None
