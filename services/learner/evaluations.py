"""Evaluation points in flight between the learner and the evaluator, and when one is
sent again.

The learner sends an evaluation point (weights marked `eval_point`) and keeps it until
the evaluator's metric row for it comes back. A point is sent again when it was
evidently lost: a later point was reported (its weights or its row were lost), later
points were sent and the evaluator has been silent (it holds later points until it has
the earlier ones, so no later report would come), or nothing at all came for long
(the last point's). `due` decides that from the clock alone, so it is tested in
process; the service publishes what it returns.
"""

from __future__ import annotations

import collections
import dataclasses
import threading
import time
from dataclasses import dataclass
from typing import Any

from shared.net.messages import Metrics, Weights
from shared.net.wire import WireError, decode, encode

# An evaluation point is sent again when the evaluator reported a later one (this one's
# weights or row were lost), or when nothing was reported for this long (the last one's).
EVAL_RESEND_S = 30.0
# A point with later points sent after it is resent after this much of the evaluator's
# silence: the evaluator holds later points until it has the earlier ones (rows in
# episode order), so no later report would come to show that this one was lost.
EVAL_BEHIND_RESEND_S = 5.0


def with_unreported(payload: bytes, unreported: list[int]) -> bytes:
    """A kept weights message with its list of earlier unreported points brought up to
    date for a resend: the list of when it first went out may name points whose rows
    have come since (an evaluator restarted in between would wait for them)."""
    return encode(dataclasses.replace(decode(payload, Weights), unreported=unreported))


def reported_point(payload: bytes) -> int:
    """The point an evaluator's metrics row reports (only the point is read: the API is
    the rows' consumer of record); WireError if the row is malformed."""
    return reported_row(payload)[0]


def reported_row(payload: bytes) -> tuple[int, dict[str, Any], int | None]:
    """The point an evaluator's metrics row reports, the row and the attempt of the run
    it is of; WireError if malformed."""
    msg = decode(payload, Metrics)
    point = msg.data.get("episode") if isinstance(msg.data, dict) else None
    if not isinstance(point, int) or isinstance(point, bool):
        raise WireError(f"metrics: eval row episode is not an int: {point!r}")
    return point, msg.data, msg.attempt


@dataclass(frozen=True)
class PointRow:
    """What the learner reads of a point's row for `early_stop`: its success (the best
    point's weights go to best.pt), its steps, and its `stop_reason` (the evaluator read
    the run's rule on its rows: the run ends there), None without one."""

    episode: int
    env_steps: int
    success_rate: float
    stop_reason: str | None

    @classmethod
    def of(cls, point: int, data: dict[str, Any]) -> PointRow:
        why = data.get("stop_reason")
        try:
            steps, success = int(data["env_steps"]), float(data["success_rate"])
        except (KeyError, TypeError, ValueError, OverflowError) as err:  # (int(inf))
            raise WireError(f"metrics: eval row of point {point}: {err!r}") from None
        return cls(point, steps, success, why if isinstance(why, str) and why else None)

    def as_row(self) -> dict[str, Any]:
        return {
            "episode": self.episode,
            "env_steps": self.env_steps,
            "success_rate": self.success_rate,
        }


class EvaluationsInFlight:
    """Evaluation points sent to the evaluator that it has not reported yet.

    `sent` and `due` are called on the learner's thread, `reported` on Zenoh's (from the
    evaluator's metric rows): what they read and write of the points is under one lock
    (`due` once snapshotted the points, re-encoded them, then wrote them back, so a row
    reported in between was undone, and a row could change the map while it was
    iterated). A point unreported after `max_s` no longer counts (a slow or absent
    evaluator must not mark every update)."""

    def __init__(self, max_s: float = 1.0, early_stop: bool = False) -> None:
        self.max_s = max_s
        self.last_sent = -1
        self.sent_at = 0.0
        self.last_reported = -1
        self.reported_rows = 0
        # Points sent and not reported yet: point -> (when sent, the weights message).
        # Read as a whole (`if unreported`) from the learner's thread; written under
        # `_lock` only.
        self.unreported: dict[int, tuple[float, bytes]] = {}
        self.reported_at = time.monotonic()
        # `early_stop`: each point's row once, in the order they came, until the learner's
        # thread has read it (appended here before the point leaves `unreported`, so the
        # learner holds the next step until it has: lockstep.ready).
        self.early_stop = early_stop
        self.rows_in: collections.deque[PointRow] = collections.deque()
        self._rows_seen: set[int] = set()
        self._lock = threading.Lock()

    def sent(self, point: int, payload: bytes | None = None) -> None:
        """Point `point` went out (noted before it goes: its row may come back at once),
        its weights message `payload` kept until the row comes."""
        with self._lock:
            now = time.monotonic()
            if payload is not None:
                self.unreported[point] = (now, payload)
            self.last_sent, self.sent_at = point, now

    def unreported_before(self, point: int) -> list[int]:
        """The points before `point` sent and not reported yet, in order."""
        with self._lock:
            return sorted(p for p in self.unreported if p < point)

    def reported(self, point: int, data: dict[str, Any] | None = None) -> None:
        """The evaluator's row for `point` came (on Zenoh's thread); WireError, with
        nothing changed, if `early_stop` reads it and it is malformed."""
        row = PointRow.of(point, data) if self.early_stop and data is not None else None
        with self._lock:
            if row is not None and point not in self._rows_seen:
                self.rows_in.append(row)  # (a repeated row: once)
                self._rows_seen.add(point)
            self.last_reported = max(self.last_reported, point)
            self.reported_rows += 1
            self.unreported.pop(point, None)
            self.reported_at = time.monotonic()

    def busy(self) -> bool:
        """The evaluator is (most likely) evaluating a point we sent."""
        return self.last_reported < self.last_sent and time.monotonic() - self.sent_at < self.max_s

    def due(self, now: float, at_once: bool = False) -> list[tuple[int, bytes]]:
        """The points to send again now, each with its list of earlier unreported points
        brought up to date (noted as sent now): those older than one the evaluator
        reported, those older than one sent since once the evaluator has been silent
        for EVAL_BEHIND_RESEND_S, or the last ones once it has been silent for
        EVAL_RESEND_S (a merely slow evaluator reports in order, so it is rarely sent
        duplicates, which it drops); with `at_once` all of them (it just came back).
        Decided on a snapshot and re-encoded outside the lock (milliseconds); a point
        reported meanwhile is neither noted again nor sent."""
        with self._lock:
            points = sorted(self.unreported.items())
            quiet = now - self.reported_at
            last_reported, last_sent = self.last_reported, self.last_sent
        out = []
        for point, entry in points:
            sent, payload = entry
            overtaken = point < last_reported and now - sent > 2.0  # (give a resend time)
            waited = min(quiet, now - sent)  # silence since this point and since a row
            held = point < last_sent and waited > EVAL_BEHIND_RESEND_S
            if not (at_once or overtaken or held or waited > EVAL_RESEND_S):
                continue
            payload = with_unreported(payload, self.unreported_before(point))
            with self._lock:
                if self.unreported.get(point) is not entry:
                    continue  # reported (or sent anew) while it was re-encoded
                self.unreported[point] = (now, payload)
            out.append((point, payload))
        return out
