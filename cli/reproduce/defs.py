"""What a figure of the thesis is, as data: its arms (config files), the metric it
draws, the claims section 6 makes about it and the profiles it runs under.

An arm is a config file under configs/ (read, never restated: cli/reproduce/experiments.py),
so `macb run FILE` and `macb reproduce FIGURE` run the same thing. The figures themselves
are in cli/reproduce/figures.py, the checks their claims use in cli/reproduce/claims.py.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

PROFILES = ("mpe2", "thesis")


@dataclass(frozen=True)
class ArmDef:
    name: str  # its name in the API, the legend and the report
    file: str  # its config, under configs/
    thesis: str = ""  # what the thesis reports for it ("" : not in the thesis)
    row: str = ""  # table figures: the cell it fills
    col: str = ""
    # An arm read from its runs rather than a file (the figure view of any runs folder
    # or experiment, cli/view.py): its config keys; None for an arm of configs/.
    config: dict[str, Any] | None = field(default=None, compare=False)


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
    # The band drawn around each arm's mean (cli/reproduce/analysis.py BANDS): "std",
    # or "ci75", the thesis's 75% confidence interval over seeds (§6 l.373, seaborn).
    band: str = "std"

    def arm(self, name: str) -> ArmDef:
        (arm,) = [a for a in self.arms if a.name == name]
        return arm
