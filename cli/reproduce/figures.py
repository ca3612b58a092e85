"""The thesis's figures as data: each one's arms, the metric it draws and the claims
section 6 makes about it, in the thesis's words with the numbers it reports.

The keys all of a figure's files share become the experiment's base and each arm sets
the rest (cli/reproduce/experiments.py). Every count-bonus arm has a control beside it:
the constant bonus with the same beta and reward (one per distinct pair), which says
whether the counting or the mere reward shift does the work. cli/reproduce/analysis.py
measures the claims; tests/test_figures.py checks these definitions.
"""

from __future__ import annotations

from cli.reproduce.claims import (
    Cell,
    ConvergesBefore,
    ConvergesNear,
    CountOneGrows,
    DecreasesAfterPeak,
    FasterThan,
    LowerAtEnd,
    MostBeat,
    NoLearning,
    PeaksAt,
    PlateauNear,
    ReachesSooner,
    SameAs,
    ValueAt,
)
from cli.reproduce.defs import PROFILES, ArmDef, Claim, FigureDef

__all__ = ["FIGURES", "PROFILES", "FigureDef"]


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
    band="ci75",
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
