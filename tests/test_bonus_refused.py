"""A bonus query the counter refuses is told apart from one nobody answered in time.

A real counter process on a real router: it answers a query it cannot price (a run it
does not serve, a payload that is not a query) with an error reply saying why, which
the learner's `BonusClient` counts as `refused` and logs once per reason; a counter
that does not answer at all (stopped) leaves the query `unanswered`. Both are priced
again later, as before; only what the learner reports differs.
"""

from __future__ import annotations

import logging
import signal
import threading

import numpy as np

from services.learner.bonus import BonusClient, bus_query
from shared.core.replay import Batch
from shared.net import bus as keys
from shared.net.bus import Bus, Refused, Replies
from shared.net.messages import BonusQuery
from shared.net.wire import encode
from tests.harness import wait_for, wait_services


def _batch(rows: int = 4) -> Batch:
    rng = np.random.default_rng(0)
    return Batch(
        obs=rng.normal(size=(rows, 3)).astype(np.float32),
        act=rng.normal(size=(rows, 2)).astype(np.float32),
        rew=np.zeros(rows, np.float32),
        next_obs=np.zeros((rows, 3), np.float32),
        done=np.zeros(rows, np.float32),
        idx=np.arange(rows),
    )


def test_a_refused_query_says_why_and_a_silent_one_is_unanswered(cluster, bus, caplog):
    cluster.service("counter", "c0")
    wait_services(bus, 1)
    key = keys.k_bonus("r-unknown")

    # a run the counter does not serve: refused at once, saying so
    query = encode(BonusQuery("r-unknown", obs=np.zeros((4, 3), np.float32),
                              act=np.zeros((4, 2), np.float32)))  # fmt: skip
    got = bus.collect_all(bus.get_async(key, query, timeout=2.0))
    assert got.ok == [] and [r.by for r in got.refused] == ["c0"], got
    assert "r-unknown" in got.refused[0].reason, got.refused
    # not a query at all: refused with the decoder's reason
    garbage = bus.collect_all(bus.get_async(key, b"\x00garbage\xff", timeout=2.0))
    assert garbage.ok == [] and len(garbage.refused) == 1 and garbage.refused[0].reason, garbage

    client = BonusClient(bus_query(bus, key), print, "r-unknown", "cen-macb", 0.8, 2, "c0")
    with caplog.at_level(logging.WARNING, logger="services.learner.bonus"):
        assert client.bonus_for([_batch(), _batch()]) is None
        assert client.bonus_for([_batch()]) is None
    assert (client.refused, client.unanswered, client.failures) == (2, 0, 0)
    said = [r.getMessage() for r in caplog.records if "refused a bonus query" in r.getMessage()]
    assert len(said) == 1 and "r-unknown" in said[0], "each reason logged once"

    # A counter per node answers every run's key: another counter's refusal is not the
    # run's counter's word (it does not serve the run), so it leaves the query unanswered.
    cluster.service("counter", "c1", name="counter1")
    wait_services(bus, 2)

    def refused_by_both():  # (asked again: c1 may answer its info before its first query)
        got = bus.collect_all(bus.get_async(key, query, timeout=2.0))
        return got if sorted(r.by for r in got.refused) == ["c0", "c1"] else None

    both = wait_for(refused_by_both, timeout=30, what="both counters' refusals")
    assert both.ok == [], both
    elsewhere = BonusClient(bus_query(bus, key), print, "r-unknown", "cen-macb", 0.8, 2, "c9")
    assert elsewhere.bonus_for([_batch()]) is None
    assert (elsewhere.refused, elsewhere.unanswered) == (0, 1)
    cluster.kill("counter1", signal.SIGTERM)

    # a counter that answers nothing (stopped): Zenoh's own timeout is no refusal
    quick = BonusClient(bus_query(bus, key, timeout=0.5), print, "r-unknown", "cen-macb", 0.8,
                        2, "c0")  # fmt: skip
    pause = threading.Thread(target=cluster.pause, args=("c0",), kwargs={"seconds": 2.0})
    pause.start()
    try:
        threading.Event().wait(0.3)  # the SIGSTOP has landed
        assert quick.bonus_for([_batch()]) is None
    finally:
        pause.join()
    assert (quick.refused, quick.unanswered) == (0, 1)
    # and it still refuses once it runs again
    again = bus.collect_all(bus.get_async(key, query, timeout=2.0))
    assert len(again.refused) == 1, again


def test_a_handlers_refusal_reaches_the_asker_and_other_errors_do_not(router):
    """The bus's side on its own: `Refused` from a handler is an error reply marked as
    ours; a handler that raises or returns None sends nothing."""
    a, b = Bus([router]), Bus([router])
    try:
        b.queryable("t/refuse", lambda k, p: Refused("b", f"no {p.decode()}: none"))
        b.queryable("t/raise", lambda k, p: 1 / 0)
        b.queryable("t/ok", lambda k, p: b"yes")
        wait = threading.Event()
        for _ in range(50):  # the queryables are declared through the router
            if a.collect_all(a.get_async("t/ok", b"", timeout=1.0)).ok:
                break
            wait.wait(0.1)
        refused = a.collect_all(a.get_async("t/refuse", b"x", timeout=1.0))
        assert refused == Replies([], [Refused("b", "no x: none")]), refused
        assert a.collect_all(a.get_async("t/raise", b"x", timeout=1.0)) == Replies()
        assert a.get("t/refuse", b"x", timeout=1.0) == []  # `get` keeps only ok replies
    finally:
        a.close()
        b.close()
