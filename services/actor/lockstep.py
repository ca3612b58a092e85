"""The lockstep handshake: one act request open at a time, the learner's answer to it.

In lockstep the actor steps only with the action the learner computed for that step
(`act_request` -> `action`). A request with no answer goes out again after
ACT_RESEND_S; an answer to a request other than the open one (a resend's twin, already
taken) is dropped. A lone lockstep actor and a group's actor ask alike, so the rule is
kept here, on the clock it is given, and tested without a bus.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ACT_RESEND_S = 1.0  # an act request with no answer is sent again


@dataclass
class ActExchange:
    """The open request (seq, first sent, last sent) and the answer taken for it."""

    asked: tuple[int, float, float] | None = None
    action: tuple[int, np.ndarray] | None = None
    wait_s: float = 0.0  # summed time from a request's first sending to its answer

    def awaits(self, seq: int) -> bool:
        """An answer for step `seq` is the one wanted now."""
        return self.asked is not None and seq == self.asked[0]

    def answer(self, seq: int, act: np.ndarray) -> None:
        self.action = (seq, act.astype(np.float32, copy=False))

    def take(self, seq: int, now: float) -> np.ndarray | None:
        """The answer for step `seq` if it has come (the request is then closed)."""
        if self.action is None or self.asked is None or self.action[0] != seq:
            return None
        act = self.action[1]
        self.wait_s += now - self.asked[1]
        self.action = self.asked = None
        return act

    def ask(self, seq: int, now: float) -> bool:
        """True if a request for step `seq` is to go out now: none is open, or the open
        one has had no answer for ACT_RESEND_S (it keeps its first sending time)."""
        if self.asked is not None and now - self.asked[2] <= ACT_RESEND_S:
            return False
        self.asked = (seq, now if self.asked is None else self.asked[1], now)
        return True

    def forget(self) -> None:
        """Rejoined elsewhere: no request is open."""
        self.asked = self.action = None


def valid_action(act: np.ndarray, shape: tuple[int, ...]) -> bool:
    """An answer the actor can step with: the shape it asked for, finite values."""
    return act.shape == shape and bool(np.isfinite(act).all())
