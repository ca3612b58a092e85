"""Other services' liveliness as a service sees it: who went away, who came back, and
who stayed away past the grace, by `PeerGrace`, the rule the API and `macb start` use.

A peer whose token goes away is given the grace to come back before its runs are given
up: a restarted service, or a restarted router (every token vanishes with it), costs a
pause, not the run.
"""

from __future__ import annotations

from typing import NamedTuple

from shared.net.monitor import PeerGrace, live_peer

CHECK_S = 0.25  # how often peers away are looked at while any is


class Seen(NamedTuple):
    role: str
    peer: str
    back: bool  # its token came back after it had gone away


class PeerWatch:
    """The peers away now (with when they went) and when they were last looked at."""

    def __init__(self, grace_s: float) -> None:
        self.grace = PeerGrace(grace_s)
        self._checked = 0.0

    def seen(self, key: str, alive: bool, now: float) -> Seen | None:
        """A liveliness token appeared (`alive`) or went away; None for a key that is
        not a service's."""
        found = live_peer(key)
        if found is None:
            return None
        role, peer = found
        if alive:
            return Seen(role, peer, self.grace.back(peer))
        self.grace.lost(role, peer, now)
        return Seen(role, peer, False)

    def given_up(self, now: float) -> list[tuple[str, str]]:
        """(role, peer) of the peers away past the grace (forgotten from then on);
        looked at no more than every CHECK_S."""
        if not self.grace or now - self._checked <= CHECK_S:
            return []
        self._checked = now
        return self.grace.expired(now)

    def clear(self) -> None:
        self.grace.clear()
