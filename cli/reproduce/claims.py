"""The checks a figure's claims use: each measures one claim of the thesis on the
analysed figure (cli/reproduce/analysis.py, `Analysis`).

measure() gives the measured text and True/False (None: cannot tell from these runs);
`needs` is the training episodes a run must reach for the verdict to count (shorter:
"not run to that length", cli/reproduce/analysis.py `claim_verdicts`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class OneArm:
    """A claim about one arm (its first field)."""

    arm: str

    def arms(self) -> tuple[str, ...]:
        return (self.arm,)


class AtEpisode:
    """A claim about the value at `episode`: the runs must reach that episode."""

    episode: int

    @property
    def needs(self) -> int:
        return self.episode


@dataclass(frozen=True)
class ConvergesNear(OneArm):
    lo: int
    hi: int
    needs: int

    def measure(self, a: Any) -> tuple[str, bool | None]:
        conv = a.arm(self.arm).converged
        if conv is None:
            return f"{self.arm}: {a.arm(self.arm).describe()}", False
        return f"{self.arm}: {conv:,} episodes", self.lo <= conv <= self.hi


@dataclass(frozen=True)
class ConvergesBefore:
    arms_: tuple[str, ...]
    before: int
    needs: int

    def arms(self) -> tuple[str, ...]:
        return self.arms_

    def measure(self, a: Any) -> tuple[str, bool | None]:
        convs = {n: a.arm(n).converged for n in self.arms_}
        text = "; ".join(f"{n}: {_episodes(c)}" for n, c in convs.items())
        return text, all(c is not None and c < self.before for c in convs.values())


@dataclass(frozen=True)
class FasterThan:
    arms_: tuple[str, ...]
    ref: str
    needs: int
    fastest: tuple[str, ...] = ()  # the fastest of arms_ must be one of these

    def arms(self) -> tuple[str, ...]:
        return (*self.arms_, self.ref)

    def measure(self, a: Any) -> tuple[str, bool | None]:
        ref = a.arm(self.ref).converged
        convs = {n: a.arm(n).converged for n in self.arms_}
        text = f"{self.ref}: {_episodes(ref)}; " + "; ".join(
            f"{n}: {_episodes(c)}" for n, c in convs.items()
        )
        inf = float("inf")
        ok = all(
            (c if c is not None else inf) < (ref if ref is not None else inf)
            for c in convs.values()
        )
        ok = ok and all(c is not None for c in convs.values())
        if self.fastest and ok:
            best = min(convs, key=lambda n: convs[n])
            text += f"; fastest: {best}"
            ok = best in self.fastest
        return text, ok


@dataclass(frozen=True)
class NoLearning(OneArm):
    needs: int
    below: float = 0.1

    def measure(self, a: Any) -> tuple[str, bool | None]:
        plateau = a.arm(self.arm).plateau
        return f"{self.arm}: plateau {plateau:.0%}", plateau < self.below


@dataclass(frozen=True)
class ReachesSooner:
    """Each arm reaches 90% of ref's plateau within `ratio` of the episodes ref needs."""

    arms_: tuple[str, ...]
    ref: str
    ratio: float
    needs: int

    def arms(self) -> tuple[str, ...]:
        return (*self.arms_, self.ref)

    def measure(self, a: Any) -> tuple[str, bool | None]:
        ref = a.arm(self.ref)
        if ref.converged is None:
            return f"{self.ref}: {ref.describe()}", False
        target = 0.9 * ref.plateau
        parts, ok = [f"{self.ref}: {ref.converged:,} episodes to {target:.0%}"], True
        for n in self.arms_:
            e = a.arm(n).first_reaching(target)
            parts.append(f"{n}: {_episodes(e)}" + (f" ({e / ref.converged:.2f}x)" if e else ""))
            ok = ok and e is not None and e <= self.ratio * ref.converged
        return "; ".join(parts), ok


@dataclass(frozen=True)
class PlateauNear:
    arm: str
    lo: float
    hi: float
    needs: int
    below: str = ""  # and under this arm's plateau

    def arms(self) -> tuple[str, ...]:
        return (self.arm, self.below) if self.below else (self.arm,)

    def measure(self, a: Any) -> tuple[str, bool | None]:
        p = a.arm(self.arm).plateau
        text, ok = f"{self.arm}: plateau {p:.0%}", self.lo <= p <= self.hi
        if self.below:
            q = a.arm(self.below).plateau
            text += f"; {self.below}: {q:.0%}"
            ok = ok and p < q
        return text, ok


@dataclass(frozen=True)
class SameAs:
    """Two arms perform alike: plateaus within 0.1 and convergence within `tol`."""

    first: str
    second: str
    needs: int
    tol: float = 0.25

    def arms(self) -> tuple[str, ...]:
        return (self.first, self.second)

    def measure(self, a: Any) -> tuple[str, bool | None]:
        x, y = a.arm(self.first), a.arm(self.second)
        text = f"{self.first}: {x.describe()}; {self.second}: {y.describe()}"
        ok = abs(x.plateau - y.plateau) <= 0.1
        if x.converged is not None and y.converged is not None:
            ok = ok and abs(x.converged - y.converged) <= self.tol * max(x.converged, y.converged)
        else:
            ok = ok and x.converged is None and y.converged is None
        return text, ok


@dataclass(frozen=True)
class DecreasesAfterPeak(OneArm):
    needs: int
    drop: float = 0.1

    def measure(self, a: Any) -> tuple[str, bool | None]:
        x = a.arm(self.arm)
        return f"{self.arm}: peak {x.peak:.0%}, final {x.final:.0%}", x.peak - x.final >= self.drop


@dataclass(frozen=True)
class ValueAt(OneArm, AtEpisode):
    episode: int
    lo: float
    hi: float

    def measure(self, a: Any) -> tuple[str, bool | None]:
        x = a.arm(self.arm)
        v, at = x.value_at(self.episode)
        if v is None:
            return f"{self.arm}: no point", None
        return f"{self.arm}: {v:.0%} at {at:,}", self.lo <= v <= self.hi


@dataclass(frozen=True)
class LowerAtEnd:
    """At the end (the metric's last value), arm < ratio x ref, for each (arm, ref)."""

    pairs: tuple[tuple[str, str], ...]
    ratio: float
    needs: int

    def arms(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(n for p in self.pairs for n in p))

    def measure(self, a: Any) -> tuple[str, bool | None]:
        parts, ok = [], True
        for arm, ref in self.pairs:
            x, r = a.arm(arm).final, a.arm(ref).final
            rel = f" ({x / r:.2f}x)" if r else ""
            parts.append(f"{arm}: {x:,.0f} vs {ref}: {r:,.0f}{rel}")
            ok = ok and x < self.ratio * r
        return "; ".join(parts), ok


@dataclass(frozen=True)
class Cell(OneArm, AtEpisode):
    """A table cell after `episode` episodes: success within 0.15, count-1 within 10
    points of the thesis's (3 seeds x 10 evaluation episodes are noisy)."""

    episode: int
    sr: float
    c1: float | None  # percent; None: the thesis gives none

    def measure(self, a: Any) -> tuple[str, bool | None]:
        x = a.arm(self.arm)
        v, at = x.value_at(self.episode)
        c1, _ = x.value_at(self.episode, "count1_pct")
        if v is None:
            return f"{self.arm}: no point", None
        ok = abs(v - self.sr) <= 0.15
        text = f"{v:.0%}"
        if self.c1 is not None:
            text += f", {c1:.0f}%" if c1 is not None else ", -"
            ok = ok and c1 is not None and abs(c1 - self.c1) <= 10
        return f"{text} (at {at:,})", ok


@dataclass(frozen=True)
class MostBeat(AtEpisode):
    arms_: tuple[str, ...]
    ref: str
    episode: int

    def arms(self) -> tuple[str, ...]:
        return (*self.arms_, self.ref)

    def measure(self, a: Any) -> tuple[str, bool | None]:
        ref, _ = a.arm(self.ref).value_at(self.episode)
        vals = [a.arm(n).value_at(self.episode)[0] for n in self.arms_]
        if ref is None or None in vals:
            return "no points", None
        wins = sum(v > ref for v in vals)
        return f"{wins} of {len(vals)} cells above {self.ref}'s {ref:.0%}", wins > len(vals) / 2


@dataclass(frozen=True)
class PeaksAt(AtEpisode):
    """For each k, success at the peak beta exceeds success at the beta before it."""

    pairs: tuple[tuple[str, str], ...]  # (arm at the peak beta, arm at the beta before)
    episode: int

    def arms(self) -> tuple[str, ...]:
        return tuple(n for p in self.pairs for n in p)

    def measure(self, a: Any) -> tuple[str, bool | None]:
        parts, ok = [], True
        for peak, before in self.pairs:
            x, y = a.arm(peak).value_at(self.episode)[0], a.arm(before).value_at(self.episode)[0]
            if x is None or y is None:
                return "no points", None
            parts.append(f"{peak}: {x:.0%} > {before}: {y:.0%}")
            ok = ok and x > y
        return "; ".join(parts), ok


@dataclass(frozen=True)
class CountOneGrows(AtEpisode):
    """count-1 % does not fall as k grows (per beta), and is >= 99% at the largest k."""

    rows: tuple[tuple[str, ...], ...]  # per beta, its arms in increasing k
    episode: int

    def arms(self) -> tuple[str, ...]:
        return tuple(n for r in self.rows for n in r)

    def measure(self, a: Any) -> tuple[str, bool | None]:
        ok, parts = True, []
        for row in self.rows:
            c1 = [a.arm(n).value_at(self.episode, "count1_pct")[0] for n in row]
            if None in c1:
                return "no points", None
            parts.append("/".join(f"{c:.0f}" for c in c1))
            ok = ok and all(x <= y + 1.0 for x, y in zip(c1, c1[1:])) and c1[-1] >= 99.0
        return "count-1 % by k, per beta: " + "; ".join(parts), ok


def _episodes(e: int | None) -> str:
    return "no plateau" if e is None else f"{e:,}"
