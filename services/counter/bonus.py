"""Bonus queries: counts and bonuses for rows the learner samples, answered on Zenoh's
thread while the service thread counts.

A query reads the tables under the lock ingestion counts under, so it sees a burst
counted whole or not at all. Queries come first, since the learner waits for them: while
any is being answered the service thread steps aside between the steps of its work
(`QueryGate`). A row the counter has never counted is priced as n = 1 and tallied.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from services.counter.state import RunState
from shared.net.messages import BonusQuery, BonusReply
from shared.net.wire import WireError, check_dims, encode

# The longest the service thread steps aside for one bonus query being answered.
QUERY_YIELD_MAX_S = 0.005


class QueryGate:
    """How many bonus queries are being answered now, for the service thread to wait on."""

    def __init__(self, max_wait_s: float = QUERY_YIELD_MAX_S) -> None:
        self.max_wait_s = max_wait_s
        self._lock = threading.Lock()
        self._now = 0
        self._none = threading.Event()
        self._none.set()

    @contextmanager
    def answering(self) -> Iterator[None]:
        """Around one query's answer, on Zenoh's thread."""
        with self._lock:
            self._now += 1
            self._none.clear()
        try:
            yield
        finally:
            with self._lock:
                self._now -= 1
                if not self._now:
                    self._none.set()

    def step_aside(self) -> None:
        """Wait (at most `max_wait_s`) while a query is being answered.

        Whenever the query's thread gives up the GIL (a matrix product, a forced
        switch), the busy service thread would take it and keep it for a whole switch
        interval, and on a loaded machine each such handoff also waits for the OS to
        wake the query's thread: stepping aside shortens the handler's tail under a
        flood (docs/performance.md, "Counter service").
        """
        if not self._none.is_set():
            self._none.wait(self.max_wait_s)


def check(st: RunState, msg: BonusQuery) -> None:
    """WireError unless the query's rows are (B, dim) of the run's layout."""
    obs, act = msg.obs, msg.act
    if obs.ndim != 2 or act.ndim != 2 or len(obs) != len(act):
        raise WireError("bonus_query: obs and act must be (B, dim) with the same B")
    check_dims(msg, st.obs_dim, st.act_dim)


def answer(
    st: RunState, msg: BonusQuery, lock: threading.RLock, t0: float, service: str
) -> bytes | None:
    """The encoded reply to a checked query (None if the run was closed meanwhile),
    naming the counter that answers (`service`); its time since `t0` and its rows never
    counted go to the run's stats."""
    batch = len(msg.obs)
    keys = st.explorer.keys(msg.obs, msg.act)  # no lock: hashers are read-only
    with lock:
        if st.closed:
            return None
        counts = [t.counts(k) for t, k in zip(st.explorer.tables, keys)]
    if counts:
        counts_arr = np.stack(counts).astype(np.int64)
        uncounted = int(np.sum(np.any(counts_arr < 1, axis=0)))
    else:  # the control arm counts nothing
        counts_arr = np.zeros((0, batch), np.int64)
        uncounted = 0
    bonus = st.explorer.bonus_from_counts([np.maximum(c, 1) for c in counts], batch)
    with lock:
        tables = st.explorer.stats()  # O(1): kept up to date as keys are counted
    bonus32 = bonus.astype(np.float32)
    reply = encode(
        BonusReply(msg.run, counts=counts_arr, bonus=bonus32, tables=tables, service=service)
    )
    elapsed = time.perf_counter() - t0
    with lock:
        st.latencies.append(elapsed)
        st.queries += 1
        st.uncounted_rows_queried += uncounted
    return reply
