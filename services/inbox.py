"""A service thread's side of its messages: taken off the queue in bursts, and the
dropped ones counted.

Zenoh's callbacks only put (tag, key, payload) on the queue. The service thread takes
them without waiting while a burst is under way or it has work of its own, and learns
when a burst has drained, for work cheaper done once a burst than once a message.
"""

from __future__ import annotations

import queue
import threading
from collections import Counter
from typing import Literal

Item = tuple[str, str, bytes]  # tag, key expression, payload
DRAINED: Literal["drained"] = "drained"
WAKE: Item = ("wake", "", b"")  # no message: wakes a thread waiting in `take`


def wake(q: queue.Queue[Item] | queue.SimpleQueue[Item]) -> None:
    """Wake the thread waiting on `q` (from a signal handler: the loop then sees its stop).

    CPython 3.11's `SimpleQueue.get(timeout=...)`, interrupted by a signal whose handler
    ends after the timeout, waits again with a negative timeout, which is no timeout: only
    a put ends it. Its put is reentrant, safe in a handler. A `Queue`'s wait ends by its
    timeout, and its put takes a lock the interrupted thread may hold: not put there."""
    if isinstance(q, queue.SimpleQueue):
        q.put(WAKE)


class Inbox:
    """The queue, and whether a burst (messages taken since it was last found empty) is
    under way."""

    def __init__(self, q: queue.Queue[Item] | queue.SimpleQueue[Item]) -> None:
        self.queue = q
        self.in_burst = False

    def take(self, busy: bool, wait_s: float) -> Item | Literal["drained"] | None:
        """The next message; DRAINED, once, when the queue is found empty after a burst;
        None when it is empty otherwise (after waiting up to `wait_s`, unless `busy` or
        in a burst: then it does not wait)."""
        try:
            if busy or self.in_burst:
                item = self.queue.get_nowait()
            else:
                item = self.queue.get(timeout=wait_s)
        except queue.Empty:
            if self.in_burst:
                self.in_burst = False
                return DRAINED
            return None
        if item is WAKE:
            return None
        self.in_burst = True
        return item


# Reasons kept apart in the tally; drops for any further reason are counted under
# OTHER_REASONS, so garbage cannot grow the tally (and every info reply) without bound.
MAX_REASONS = 64
REASON_CHARS = 80  # a reason's bucket is at most this long
OTHER_REASONS = "other reasons"


def reason_bucket(reason: str) -> str:
    """The tally's bucket of a drop's reason: its fixed text, before the first ':'.
    Every reason puts what varies (a run, a value the sender chose) after the colon, so
    a sender cannot open a bucket per message."""
    return reason.split(":", 1)[0][:REASON_CHARS]


class Rejects:
    """Messages dropped, by reason (`reason_bucket`: the text before its first ':'), in
    at most MAX_REASONS buckets (the rest under OTHER_REASONS). Safe from any thread
    (the counter drops bonus queries on Zenoh's); says when a drop should be logged, at
    most once every `log_every_s`, so a flood of garbage does not flood the log."""

    def __init__(self, log_every_s: float = 1.0, max_reasons: int = MAX_REASONS) -> None:
        self.by_reason: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._log_every_s = log_every_s
        self._max_reasons = max_reasons
        self._last_log = 0.0

    def add(self, reason: str, now: float) -> int | None:
        """Count one drop; the total so far if it is to be logged now, else None."""
        bucket = reason_bucket(reason)
        with self._lock:
            if bucket not in self.by_reason and len(self.by_reason) >= self._max_reasons - 1:
                bucket = OTHER_REASONS  # (the last bucket: every reason beyond the others)
            self.by_reason[bucket] += 1
            if now - self._last_log > self._log_every_s:
                self._last_log = now
                return sum(self.by_reason.values())
        return None

    def counts(self) -> tuple[dict[str, int], int]:
        """Drops by reason, and their total, read together."""
        with self._lock:
            return dict(self.by_reason), sum(self.by_reason.values())
