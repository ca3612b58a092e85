"""The learner's bonus queries: a tick's minibatches priced by the counter in one round
trip (sample time: the counts then), or locally for the arms that count nothing.

A run group's runs `ask` at once and then take their `answer`s, so their round trips
overlap. A query the counter does not answer is kept (`PendingBonus`) and priced again,
never redrawn: the sampler's stream stays the one per-update sampling gives. The client
holds no service: it is given the query to send (`bus_query` makes one on a bus) and
where a malformed reply is reported.

Every counter answers the run's key, so a reply is taken only from the run's counter
(`BonusReply.service`): another one may hold this run's tables of an ended attempt,
restored from its disk. A query names the run's attempt, which such a counter refuses;
a bonus that is not finite and >= 0 is refused here.
"""

from __future__ import annotations

import collections
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from shared.net.bus import Replies
from shared.net.messages import BonusQuery, BonusReply
from shared.net.wire import WireError, decode, encode

log = logging.getLogger(__name__)

# Sends a query's payload to the run's counter; returns the wait for its replies.
Query = Callable[[bytes], Callable[[], Replies]]
QUERY_TIMEOUT_S = 2.0


def bus_query(bus: Any, key: str, timeout: float = QUERY_TIMEOUT_S) -> Query:
    """A query on `bus` (`get_async`, then `collect_all` its replies) at `key`."""

    def query(payload: bytes) -> Callable[[], Replies]:
        replies = bus.get_async(key, payload, timeout=timeout)
        return lambda: bus.collect_all(replies)

    return query


class BonusClient:
    """Bonus queries to the counter for sampled batches (local for none/constant).
    `query` sends one (`bus_query`), `reject(why)` reports a malformed reply."""

    def __init__(
        self,
        query: Query,
        reject: Callable[[str], None],
        run: str,
        mode: str,
        beta: float,
        n: int,
        counter: str | None = None,
        attempt: int | None = None,
    ) -> None:
        self.query, self.reject = query, reject
        # the run's counter: only its reply or refusal counts (every node's counter
        # answers the key; the others do not serve the run, or hold an ended attempt's
        # tables). None: any counter's.
        self.counter = counter
        self.attempt = attempt  # the run's (Start.attempt), on every query
        self.run, self.mode, self.beta, self.n = run, mode, beta, n
        self.latencies: collections.deque[float] = collections.deque(maxlen=1000)
        self.wait_s = 0.0  # all time spent in queries (the learner waits for each)
        self.failures = 0  # queries answered, but by no reply the learner could use
        self.unanswered = 0  # queries no counter answered in time (priced again later)
        self.refused = 0  # queries the counter refused, saying why (priced again later)
        self.refusals: set[str] = set()  # the reasons logged (each once)
        self.queries = 0
        self.rows = 0
        # The counter's table stats as of the last answered query (its reply carries
        # them): what an evaluation point reports, without a query of its own.
        self.tables: dict[str, float] | None = None
        self.fresh = False  # tables came with this tick's query
        # Each batch's (tables, B) counts from the last answered query, for diagnostics.
        self.counts: list[np.ndarray] = []

    def bonus_for(self, batches: list) -> list[np.ndarray] | None:
        """The (B, N) bonus of each sampled batch, priced in one query; None if the
        counter did not answer."""
        return self.answer(self.ask(batches))

    def ask(self, batches: list) -> PendingBonus:
        """Send the query for `batches` (a group's runs ask at once, then take the
        answers: their round trips overlap)."""
        sizes = [len(b.rew) for b in batches]
        self.counts = [np.zeros((0, B), np.int64) for B in sizes]  # no tables to count
        if self.mode == "none":
            return PendingBonus(sizes, [np.zeros((B, self.n), np.float32) for B in sizes])
        if self.mode == "constant":
            return PendingBonus(sizes, [np.full((B, self.n), self.beta, np.float32) for B in sizes])
        obs = np.concatenate([b.obs for b in batches])
        act = np.concatenate([b.act for b in batches])
        payload = encode(BonusQuery(self.run, obs=obs, act=act, attempt=self.attempt))
        t0 = time.perf_counter()
        return PendingBonus(sizes, None, self.query(payload), t0)

    def answer(self, query: PendingBonus) -> list[np.ndarray] | None:
        """The bonuses a query asked for (waiting for its reply); None if the counter
        did not answer."""
        if query.priced is not None:
            return query.priced
        sizes, rows = query.sizes, sum(query.sizes)
        try:
            replies = query.replies()
        finally:
            self.wait_s += time.perf_counter() - query.t0
        answered = False  # the run's counter replied (an unusable reply is a failure)
        for raw in replies.ok:
            try:
                msg = decode(raw, BonusReply)
            except WireError as err:
                self.reject(str(err))
                answered = True
                continue
            if self.counter is not None and msg.service not in (None, self.counter):
                self.reject(f"bonus_reply of another counter: {msg.service}, not {self.counter}")
                continue  # (None: an older counter, which does not say)
            answered = True
            if msg.bonus.shape != (rows, self.n):
                continue
            if not (np.isfinite(msg.bonus).all() and (msg.bonus >= 0).all()):
                self.reject("bonus_reply: a bonus not finite and >= 0")
                continue
            self.latencies.append(time.perf_counter() - query.t0)
            self.queries += 1
            self.rows += rows
            self.tables = _table_stats(msg.tables)
            self.fresh = True
            bonus = msg.bonus.astype(np.float32)
            cuts = np.cumsum(sizes)[:-1]
            if msg.counts.ndim == 2 and msg.counts.shape[1] == rows:
                self.counts = np.split(msg.counts, cuts, axis=1)
            return np.split(bonus, cuts)
        if answered:
            self.failures += 1
            return None
        mine = [r for r in replies.refused if self.counter in (None, r.by)]
        if mine:
            self._refused(mine[0].reason)
        else:
            self.unanswered += 1
        return None

    def _refused(self, why: str) -> None:
        """A refusal is the counter's word on this run (a run it does not know, a
        query it cannot price): counted, and each reason logged once."""
        self.refused += 1
        if why not in self.refusals and len(self.refusals) < 16:
            self.refusals.add(why)
            log.warning("run %s: the counter refused a bonus query: %s", self.run, why)


@dataclass
class PendingBonus:
    """A bonus query sent: its batches' sizes, and the bonuses when priced here (none,
    constant) or the counter's pending replies."""

    sizes: list[int]
    priced: list[np.ndarray] | None
    replies: Callable[[], Replies] = Replies  # waits for the counter's replies
    t0: float = 0.0


def _table_stats(raw: Any) -> dict[str, float] | None:
    """The reply's optional `tables` map, if well formed (numbers under known names)."""
    names = ("table_size", "count1_pct", "counted_transitions")
    if not isinstance(raw, dict) or not all(
        isinstance(raw.get(k), int | float) and not isinstance(raw.get(k), bool) for k in names
    ):
        return None
    return {k: raw[k] for k in names}
