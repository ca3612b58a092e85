"""The thesis's figures as data: each one's arms, the metric it draws and the claims
section 6 makes about it, in the thesis's words with the numbers it reports.

An arm is a config file under configs/ (read here, never restated), so `macb run FILE`
and `macb reproduce FIGURE` run the same thing; the keys all of a figure's files share
become the experiment's base and each arm sets the rest. Every count-bonus arm has a
control beside it: the constant bonus with the same beta and reward (one per distinct
pair), which says whether the counting or the mere reward shift does the work.
`cli.report` measures the claims; tests/test_figures.py checks these definitions.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shared.config import TrainConfig, read_config_file

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
PROFILES = ("mpe2", "thesis")
MACB = ("dis-macb", "cen-macb")
# Keys only counting reads: a control (no counting) matches its MACB arm on all others.
COUNTING_KEYS = ("explore", "k", "hash", "key", "hash_round")
# Keys of a config file that are the experiment's, not one run's.
EXPERIMENT_KEYS = ("seeds",)


@dataclass(frozen=True)
class ArmDef:
    name: str  # its name in the API, the legend and the report
    file: str  # its config, under configs/
    thesis: str = ""  # what the thesis reports for it ("" : not in the thesis)
    row: str = ""  # table figures: the cell it fills
    col: str = ""


# ---------------------------------------------------------------- checks
# A check measures one claim on the analysed figure (cli.report.Analysis): measure()
# gives the measured text and True/False (None: cannot tell from these runs); `needs`
# is the training episodes a run must reach for the verdict to count.
@dataclass(frozen=True)
class ConvergesNear:
    arm: str
    lo: int
    hi: int
    needs: int

    def arms(self) -> tuple[str, ...]:
        return (self.arm,)

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
class NoLearning:
    arm: str
    needs: int
    below: float = 0.1

    def arms(self) -> tuple[str, ...]:
        return (self.arm,)

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
class DecreasesAfterPeak:
    arm: str
    needs: int
    drop: float = 0.1

    def arms(self) -> tuple[str, ...]:
        return (self.arm,)

    def measure(self, a: Any) -> tuple[str, bool | None]:
        x = a.arm(self.arm)
        return f"{self.arm}: peak {x.peak:.0%}, final {x.final:.0%}", x.peak - x.final >= self.drop


@dataclass(frozen=True)
class ValueAt:
    arm: str
    episode: int
    lo: float
    hi: float

    @property
    def needs(self) -> int:
        return self.episode

    def arms(self) -> tuple[str, ...]:
        return (self.arm,)

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
class Cell:
    """A table cell after `episode` episodes: success within 0.15, count-1 within 10
    points of the thesis's (3 seeds x 10 evaluation episodes are noisy)."""

    arm: str
    episode: int
    sr: float
    c1: float | None  # percent; None: the thesis gives none

    @property
    def needs(self) -> int:
        return self.episode

    def arms(self) -> tuple[str, ...]:
        return (self.arm,)

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
class MostBeat:
    arms_: tuple[str, ...]
    ref: str
    episode: int

    @property
    def needs(self) -> int:
        return self.episode

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
class PeaksAt:
    """For each k, success at the peak beta exceeds success at the beta before it."""

    pairs: tuple[tuple[str, str], ...]  # (arm at the peak beta, arm at the beta before)
    episode: int

    @property
    def needs(self) -> int:
        return self.episode

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
class CountOneGrows:
    """count-1 % does not fall as k grows (per beta), and is >= 99% at the largest k."""

    rows: tuple[tuple[str, ...], ...]  # per beta, its arms in increasing k
    episode: int

    @property
    def needs(self) -> int:
        return self.episode

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


@dataclass(frozen=True)
class Claim:
    text: str  # the thesis's words
    where: str  # section and line of the thesis text
    thesis: str  # the number it reports
    check: Any


@dataclass(frozen=True)
class FigureDef:
    name: str
    title: str
    section: str
    metric: str  # what the curves draw; table figures tabulate success_rate and count1_pct
    episodes: int  # the thesis's run length
    arms: tuple[ArmDef, ...]
    claims: tuple[Claim, ...]
    milestones: tuple[int, ...] = ()  # episodes the arms table reports the metric at
    kind: str = "curves"  # or "table"
    note: str = ""
    # Under `profile: thesis`, what every counting arm (Dis-/Cen-MACB) sets over its
    # file: the method the thesis's code most likely ran for this figure, where it
    # differs from the text's (docs/fidelity.md, "The thesis repo's loops, and which one
    # produced which result").
    thesis_method: tuple[tuple[str, Any], ...] = ()

    def arm(self, name: str) -> ArmDef:
        (arm,) = [a for a in self.arms if a.name == name]
        return arm


# ---------------------------------------------------------------- the figures
def _b(beta: str) -> str:
    return f"beta={beta}"


FIG3 = FigureDef(
    name="fig3",
    title="Figure 3: DDPG on sparse 1-agent navigation, beta sweep",
    section="§6.1 l.381",
    metric="success_rate",
    episodes=5000,
    arms=(
        ArmDef(_b("0.0"), "fig3/beta0.0.yaml", "rises from ~1,000, converges at ~4,000"),
        ArmDef(_b("0.2"), "fig3/beta0.2.yaml", "converges faster than beta=0.0"),
        ArmDef(_b("0.4"), "fig3/beta0.4.yaml", "converges faster than beta=0.0"),
        ArmDef(_b("0.6"), "fig3/beta0.6.yaml", "faster than beta=0.0, among the fastest"),
        ArmDef(_b("0.8"), "fig3/beta0.8.yaml", "faster than beta=0.0, among the fastest"),
        ArmDef(_b("1.2"), "fig3/beta1.2.yaml", "no learning"),
        ArmDef("constant beta=0.2 (control)", "fig3/constant0.2.yaml"),
        ArmDef("constant beta=0.4 (control)", "fig3/constant0.4.yaml"),
        ArmDef("constant beta=0.6 (control)", "fig3/constant0.6.yaml"),
        ArmDef("constant beta=0.8 (control)", "fig3/constant0.8.yaml"),
        ArmDef("constant beta=1.2 (control)", "fig3/constant1.2.yaml"),
    ),
    claims=(
        Claim(
            "the success rate of β = 0.0 starts to increase steadily from around 1000 "
            "episodes and converges at around 4000 episodes",
            "§6.1 l.381",
            "~4,000 episodes",
            ConvergesNear(_b("0.0"), 2667, 6000, needs=5000),
        ),
        Claim(
            "When β becomes larger than 0.0 and smaller than 1.0, the success rate "
            "increases faster than β = 0.0 before 1000 episodes and converges faster, "
            "especially when β = 0.6 and β = 0.8",
            "§6.1 l.381",
            "0.2-0.8 before 0.0; 0.6, 0.8 fastest",
            FasterThan(
                tuple(_b(x) for x in ("0.2", "0.4", "0.6", "0.8")),
                _b("0.0"),
                needs=5000,
                fastest=(_b("0.6"), _b("0.8")),
            ),
        ),
        Claim(
            "when β = 1.2, the agent shows no learning",
            "§6.1 l.381",
            "no learning",
            NoLearning(_b("1.2"), needs=5000),
        ),
    ),
    note="A control per beta: the constant bonus of that beta on every reward, no "
    "counting (beta 0.0's would be the same run as beta 0.0 itself). Under profile "
    "thesis the beta arms run the thesis code's fig. 3 loop (SMADDPG at 92fc6f5): the "
    "raw observation bytes as the key, priced at collection and stored with the reward "
    "(hash raw, key state, bonus_at collection); continuous observations make every key "
    "new, so that is a constant beta stored on every transition: the control's method. "
    "Under profile mpe2 they run the text's method (SimHash k 64 over o||a, priced at "
    "sample time).",
    thesis_method=(("hash", "raw"), ("key", "state"), ("bonus_at", "collection")),
)

_NAV_MACB = ("Dis-MACB", "Cen-MACB")

FIG4 = FigureDef(
    name="fig4",
    title="Figure 4: Dis-MADDPG on sparse 2-agent navigation, beta 0.7, k 64",
    section="§6.2 l.385-391",
    metric="success_rate",
    episodes=50000,
    arms=(
        ArmDef("Dis-MADDPG", "fig4/none.yaml", "converges at ~5e4"),
        ArmDef("Dis-MACB", "fig4/dis-macb.yaml", "about half the episodes (~2.5e4), most stable"),
        ArmDef("Cen-MACB", "fig4/cen-macb.yaml", "about half the episodes; plateau ~80%"),
        ArmDef("Dis-MACB without hash", "fig4/dis-macb-nohash.yaml", "about half the episodes"),
        ArmDef(
            "Dis-MADDPG, reward + 0.7",
            "fig4/offset-reward.yaml",
            "the same as Dis-MACB without hash",
        ),
        ArmDef("constant beta=0.7 (control)", "fig4/constant.yaml"),
    ),
    claims=(
        Claim(
            "although the Dis-MADDPG algorithm increases steadily, it requires around "
            "5×10^4 episodes to converge",
            "§6.2 l.385",
            "~5e4 episodes",
            ConvergesNear("Dis-MADDPG", 33333, 50000, needs=50000),
        ),
        Claim(
            "with the help of 3 different MACBs ... they only require around half of the "
            "episodes to reach the same success rate as the Dis-MADDPG",
            "§6.2 l.391, l.401 (2.5e4 against 5e4)",
            "~0.5x (2.5e4)",
            ReachesSooner(
                ("Dis-MACB", "Cen-MACB", "Dis-MACB without hash"),
                "Dis-MADDPG",
                ratio=0.67,
                needs=50000,
            ),
        ),
        Claim(
            "with Cen-MACB, the performance is slightly worse than the Dis-MACB and "
            "converges at around 80% success rate",
            "§6.2 l.391",
            "plateau ~80%, below Dis-MACB",
            PlateauNear("Cen-MACB", 0.7, 0.9, needs=50000, below="Dis-MACB"),
        ),
        Claim(
            "The Dis-MADDPG with the later reward as extrinsic reward has the same "
            "performance as the Dis-MACB without Hash",
            "§6.2 l.391",
            "the same",
            SameAs("Dis-MADDPG, reward + 0.7", "Dis-MACB without hash", needs=50000),
        ),
    ),
)

FIG6 = FigureDef(
    name="fig6",
    title="Figure 6: Cen-MADDPG on sparse 2-agent navigation, beta 0.7, k 64",
    section="§6.3 l.411",
    metric="success_rate",
    episodes=50000,
    arms=(
        ArmDef("Cen-MADDPG", "fig6/none.yaml", "fully grasps the task after ~4e4"),
        ArmDef("Dis-MACB", "fig6/dis-macb.yaml", "converges before 3e4"),
        ArmDef("Cen-MACB", "fig6/cen-macb.yaml", "converges before 3e4, then decreases"),
        ArmDef("Cen-MACB, state only", "fig6/cen-macb-state.yaml", "converges before 3e4"),
        ArmDef("constant beta=0.7 (control)", "fig6/constant.yaml"),
    ),
    claims=(
        Claim(
            "the Cen-MADDPG agents learn gradually over episodes and fully grasp the "
            "problem after around 4×10^4 episodes",
            "§6.3 l.411",
            "~4e4 episodes",
            ConvergesNear("Cen-MADDPG", 26667, 50000, needs=50000),
        ),
        Claim(
            "All of the MACB strategies can promote the speed of learning and converge "
            "before 3×10^4 episodes",
            "§6.3 l.411",
            "< 3e4 episodes",
            ConvergesBefore(("Dis-MACB", "Cen-MACB", "Cen-MACB, state only"), 30000, 50000),
        ),
        Claim(
            "if we continue training after convergence, the success rate gradually "
            "decreases (Cen-MACB: §7.3 l.491)",
            "§6.3 l.411",
            "decreases after its peak",
            DecreasesAfterPeak("Cen-MACB", needs=50000),
        ),
    ),
)

_FIG7_ARMS = (
    ("Dis-MADDPG", "fig4/none.yaml"),
    ("Dis-MADDPG + Dis-MACB", "fig4/dis-macb.yaml"),
    ("Dis-MADDPG + Cen-MACB", "fig4/cen-macb.yaml"),
    ("Dis-MADDPG + constant (control)", "fig4/constant.yaml"),
    ("Cen-MADDPG", "fig6/none.yaml"),
    ("Cen-MADDPG + Dis-MACB", "fig6/dis-macb.yaml"),
    ("Cen-MADDPG + Cen-MACB", "fig6/cen-macb.yaml"),
    ("Cen-MADDPG + constant (control)", "fig6/constant.yaml"),
)
_FIG7_THESIS = {
    "Dis-MADDPG": "fewer than Cen-MADDPG",
    "Cen-MADDPG": "more than Dis-MADDPG",
    "Cen-MADDPG + Cen-MACB": "less than half of Cen-MADDPG's",
}

FIG7 = FigureDef(
    name="fig7",
    title="Figure 7: cumulative collisions on sparse 2-agent navigation",
    section="§6.3 l.425",
    metric="collisions_cum",
    episodes=50000,
    arms=tuple(
        ArmDef(
            n,
            f,
            _FIG7_THESIS.get(n, "" if "control" in n else "vastly fewer than without MACB"),
        )
        for n, f in _FIG7_ARMS
    ),
    claims=(
        Claim(
            "our result shows that the number of collisions of the Cen-MADDPG is more "
            "than that of Dis-MADDPG",
            "§6.3 l.425",
            "Dis-MADDPG < Cen-MADDPG",
            LowerAtEnd((("Dis-MADDPG", "Cen-MADDPG"),), ratio=1.0, needs=50000),
        ),
        Claim(
            "after we apply the MACB strategies, the accumulated number of the collisions "
            "after 5×10^4 episodes vastly decreases (here: by a quarter or more)",
            "§6.3 l.425",
            "vastly fewer",
            LowerAtEnd(
                tuple(
                    (f"{algo} + {macb}", algo)
                    for algo in ("Dis-MADDPG", "Cen-MADDPG")
                    for macb in _NAV_MACB
                ),
                ratio=0.75,
                needs=50000,
            ),
        ),
        Claim(
            "especially for the Cen-MACB, which decreases the number to less than half",
            "§6.3 l.425",
            "< 0.5x",
            LowerAtEnd((("Cen-MADDPG + Cen-MACB", "Cen-MADDPG"),), ratio=0.5, needs=50000),
        ),
    ),
    note="The training runs of figures 4 and 6 (the thesis draws figure 7 from them): "
    "Dis- and Cen-MADDPG without a bonus, with each MACB and with the constant control. "
    "Collisions are colliding agent pairs summed over training steps (docs/fidelity.md E3).",
)

FIG8 = FigureDef(
    name="fig8",
    title="Figure 8: Cen-MADDPG on speaker-listener, sparse and distance rewards",
    section="§6.3 l.429-439",
    metric="success_rate",
    episodes=40000,
    milestones=(15000, 40000),
    arms=(
        ArmDef("Sparse", "fig8/sparse.yaml", "just over 40% at 4e4"),
        ArmDef("Sparse + Dis-MACB", "fig8/sparse-dis-macb.yaml", "~70% at 4e4"),
        ArmDef("Sparse + Cen-MACB", "fig8/sparse-cen-macb.yaml", "100% by 1.5e4"),
        ArmDef("Sparse + constant beta=0.8 (control)", "fig8/sparse-constant.yaml"),
        ArmDef("Distance", "fig8/dense.yaml", "rises from the start, steadily"),
        ArmDef(
            "Distance + Cen-MACB (beta=0.1)",
            "fig8/dense-cen-macb.yaml",
            "slightly worse than Distance",
        ),
        ArmDef("Distance + constant beta=0.1 (control)", "fig8/dense-constant.yaml"),
    ),
    claims=(
        Claim(
            "In the sparse reward environment, the Centralized MADDPG agents learn slowly "
            "and only surpass 40% success rate after 4×10^4 episodes of training",
            "§6.3 l.435",
            "just over 40% at 4e4",
            ValueAt("Sparse", 40000, 0.35, 0.55),
        ),
        Claim(
            "with the help of Dis-MACB the success rate increases to around 70% at 4×10^4 episodes",
            "§6.3 l.435",
            "~70% at 4e4",
            ValueAt("Sparse + Dis-MACB", 40000, 0.6, 0.8),
        ),
        Claim(
            "the agents with Cen-MACB strategy can reach 100% success rate with only "
            "1.5×10^4 episodes",
            "§6.3 l.435",
            "100% at 1.5e4",
            ValueAt("Sparse + Cen-MACB", 15000, 0.9, 1.0),
        ),
        Claim(
            "The results show that the Cen-MACB strategy makes Cen-MADDPG slightly worse "
            "in the dense reward setting",
            "§6.3 l.439",
            "Distance + Cen-MACB < Distance",
            LowerAtEnd((("Distance + Cen-MACB (beta=0.1)", "Distance"),), 1.0, needs=40000),
        ),
    ),
    note="Two controls: the constant bonus at each bonus arm's beta and reward (0.8 "
    "sparse, 0.1 distance).",
)

# Table 2 (§6.4 l.445-453): (sr %, c-1 %) after 4e4 episodes per (k, beta).
TABLE2_BETAS = ("0.05", "0.2", "0.4", "0.8")
TABLE2_KS = (32, 64, 256, 512)
TABLE2_THESIS = {
    32: ((59, 67), (60, 68), (56, 71), (53, 74)),
    64: ((72, 91), (60, 91), (34, 91), (72, 94)),
    256: ((25, 99), (82, 99), (43, 99), (81, 99)),
    512: ((75, 100), (48, 100), (75, 100), (100, 100)),
}
TABLE2_BASELINE = 47  # beta 0.0: sr 47%, no c-1


def _cell(beta: str, k: int) -> str:
    return f"beta={beta},k={k}"


TABLE2 = FigureDef(
    name="table2",
    title="Table 2: Cen-MACB + Cen-MADDPG on speaker-listener, beta x k, after 4e4 episodes",
    section="§6.4 l.443-457",
    metric="success_rate",
    episodes=40000,
    kind="table",
    arms=(
        ArmDef(_b("0.0"), "table2/beta0.0.yaml", f"{TABLE2_BASELINE}%, -", row="-", col="0.0"),
        *(
            ArmDef(
                _cell(beta, k),
                f"table2/beta{beta}_k{k}.yaml",
                "{}%, {}%".format(*TABLE2_THESIS[k][j]),
                row=str(k),
                col=beta,
            )
            for k in TABLE2_KS
            for j, beta in enumerate(TABLE2_BETAS)
        ),
        *(
            ArmDef(
                f"constant beta={beta} (control)",
                f"table2/constant{beta}.yaml",
                row="constant",
                col=beta,
            )
            for beta in TABLE2_BETAS
        ),
    ),
    claims=(
        Claim(
            "With the help of random noise exploration (β = 0.0), the agents reach around "
            "47% success rate",
            "§6.4 l.455",
            f"{TABLE2_BASELINE}%",
            Cell(_b("0.0"), 40000, TABLE2_BASELINE / 100, None),
        ),
        *(
            Claim(
                f"Table 2, β = {beta}, k = {k} (sr, c-1)",
                "§6.4 l.447-453",
                "{}%, {}%".format(*TABLE2_THESIS[k][j]),
                Cell(_cell(beta, k), 40000, TABLE2_THESIS[k][j][0] / 100, TABLE2_THESIS[k][j][1]),
            )
            for k in TABLE2_KS
            for j, beta in enumerate(TABLE2_BETAS)
        ),
        Claim(
            "the MACB method can help the agent obtain a higher success rate in most of "
            "the parameter combinations",
            "§6.4 l.455",
            "most of 16 cells above 47%",
            MostBeat(tuple(_cell(b, k) for k in TABLE2_KS for b in TABLE2_BETAS), _b("0.0"), 40000),
        ),
        Claim(
            "For three different k, they all have a peak when β = 0.8",
            "§6.4 l.457",
            "k 64, 256, 512: beta 0.8 above beta 0.4",
            PeaksAt(tuple((_cell("0.8", k), _cell("0.4", k)) for k in (64, 256, 512)), 40000),
        ),
        Claim(
            "the count-1 percentage increases when k increases and converges to 100% with "
            "k = 512 in this environment",
            "§6.4 l.457",
            "c-1 grows with k, 100% at 512",
            CountOneGrows(
                tuple(tuple(_cell(b, k) for k in TABLE2_KS) for b in TABLE2_BETAS), 40000
            ),
        ),
    ),
    note="Controls: the constant bonus at each beta of the table (a fifth row; k does not "
    "apply to a constant bonus). Figure 4's offset-reward arm shows a constant shift alone "
    "can change learning, so a cell above 47% says little until it also beats its row.",
)

FIGURES: dict[str, FigureDef] = {f.name: f for f in (FIG3, FIG4, FIG6, FIG7, FIG8, TABLE2)}


# ---------------------------------------------------------------- reading the arms
def arm_file(arm: ArmDef) -> dict[str, Any]:
    """The arm's config file as written, without the experiment's keys (seeds)."""
    data = read_config_file(CONFIGS / arm.file)
    return {k: v for k, v in data.items() if k not in EXPERIMENT_KEYS}


def arm_configs(fig: FigureDef) -> dict[str, dict[str, Any]]:
    """Every arm's config keys as its file gives them, by arm name."""
    return {a.name: arm_file(a) for a in fig.arms}


def file_seeds(fig: FigureDef) -> list[int]:
    """The seeds the figure's files list (all the same; tests check it)."""
    seeds = {json.dumps(read_config_file(CONFIGS / a.file).get("seeds")) for a in fig.arms}
    if len(seeds) != 1 or seeds == {"null"}:
        raise ValueError(f"{fig.name}: its config files list different seeds: {seeds}")
    return json.loads(seeds.pop())


def split_base(configs: dict[str, dict[str, Any]]) -> tuple[dict[str, Any], dict[str, dict]]:
    """(keys every arm sets to the same value, each arm's other keys)."""
    files = list(configs.values())
    base = {k: v for k, v in files[0].items() if all(k in f and f[k] == v for f in files[1:])}
    return base, {n: {k: v for k, v in c.items() if k not in base} for n, c in configs.items()}


COUNTING = ("dis-macb", "cen-macb")  # the explore modes that count


def profile_arm_configs(fig: FigureDef, profile: str) -> dict[str, dict[str, Any]]:
    """Every arm's config keys under a profile: its file's, and under `profile: thesis`
    the figure's `thesis_method` over each counting arm."""
    configs = arm_configs(fig)
    if profile == "thesis" and fig.thesis_method:
        method = dict(fig.thesis_method)
        configs = {
            n: {**c, **method} if c.get("explore") in COUNTING else c for n, c in configs.items()
        }
    return configs


def full_config(fig: FigureDef, arm: str, profile: str, **over: Any) -> TrainConfig:
    """An arm's whole run config under a profile (what its runs get, but the seed)."""
    configs = profile_arm_configs(fig, profile)
    return TrainConfig.model_validate({**configs[arm], "profile": profile, **over})


def experiment_body(
    fig: FigureDef,
    profile: str,
    seeds: list[int],
    episodes: int | None,
    precision: str | None = None,
) -> dict[str, Any]:
    """The POST /experiments body of a figure: the shared keys as the base, one arm per
    config file setting the rest; `episodes` (if given) cuts every run short and
    `precision` (if given) sets every run's learner precision."""
    if profile not in PROFILES:
        raise ValueError(f"unknown profile {profile!r} (profiles: {', '.join(PROFILES)})")
    base, arms = split_base(profile_arm_configs(fig, profile))
    base = {**base, "profile": profile}
    for key, value in (("episodes", episodes), ("precision", precision)):
        if value is not None:
            base[key] = value
            arms = {n: {k: v for k, v in a.items() if k != key} for n, a in arms.items()}
    return {
        **base,
        "seeds": list(seeds),
        "arms": [{"name": n, **a} for n, a in arms.items()],
    }


def select_arms(fig: FigureDef, body: dict[str, Any], patterns: list[str]) -> dict[str, Any]:
    """The body with only the arms whose name matches one of `patterns` (shell-style,
    any case: "Sparse*"), in the figure's order; ValueError naming a pattern that
    matches no arm, and the arms there are."""
    import fnmatch

    names = [a["name"] for a in body["arms"]]
    keep: set[str] = set()
    for pattern in patterns:
        hits = [n for n in names if fnmatch.fnmatch(n.lower(), pattern.lower())]
        if not hits:
            listed = "; ".join(names)
            raise ValueError(f"--arms {pattern!r}: no arm of {fig.name} matches ({listed})")
        keep.update(hits)
    return {**body, "arms": [a for a in body["arms"] if a["name"] in keep]}


def experiment_name(fig: FigureDef, body: dict[str, Any]) -> str:
    """The experiment's name, which `macb reproduce` finds it again by: the figure, the
    profile, the length, the seeds, and a digest of the whole body, so an edited config
    file makes a new experiment instead of resuming the old one."""
    digest = hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()[:8]
    length = body.get("episodes") or "full"
    seeds = ",".join(map(str, body["seeds"]))
    precision = f" precision={body['precision']}" if body.get("precision", "fp32") != "fp32" else ""
    return (
        f"reproduce {fig.name} profile={body['profile']} episodes={length} seeds={seeds}"
        f"{precision} [{digest}]"
    )


# ---------------------------------------------------------------- controls
def is_macb(config: dict[str, Any]) -> bool:
    return config.get("explore") in MACB


def control_of(fig: FigureDef, arm: str) -> str | None:
    """The constant-bonus arm whose config equals this MACB arm's but for the keys only
    counting reads (same algo, beta, reward, ...); None if it has none."""
    configs = arm_configs(fig)

    def rest(c: dict[str, Any]) -> dict[str, Any]:
        full = TrainConfig.model_validate(c).model_dump(mode="json")
        return {k: v for k, v in full.items() if k not in COUNTING_KEYS}

    mine = rest(configs[arm])
    for name, c in configs.items():
        if c.get("explore") == "constant" and rest(c) == mine:
            return name
    return None
