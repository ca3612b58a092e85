"""Arms that count nothing (`explore: none`, and the control `explore: constant`) have no
count table: their rows carry count-1 % = 0, which is no measurement. No count-1 curve
is drawn for them (the API's curves, the PNG), a table figure gives them no count-1,
and the trainer does not say of the constant arm that counting has not changed a
reward yet. A percentage axis runs 0-100."""

from __future__ import annotations

import logging
import math
import re

import httpx
import pytest

from cli.reproduce import analysis, plot, render
from cli.reproduce.figures import FIGURES
from cli.trainer import train
from services.api.main import ApiServer, Settings
from services.api.plot import draw_curves, figure_legend
from services.api.store import Store
from shared.config import make_config
from tests.harness import NETS, TINY
from tests.test_figures import synthetic

ARMS = [
    {"name": "counting", "explore": "cen-macb"},
    {"name": "control", "explore": "constant"},
    {"name": "no bonus", "explore": "none"},
]
COUNT1 = {0: 100.0, 1: 100.0, 2: 40.0}  # the counting arm's, by seed: mean 80, std 28.3


def rows(arm: str, seed: int) -> list[dict]:
    """Its points as the evaluator writes them: an arm without a table gives 0s."""
    counting = arm == "counting"
    return [
        {"episode": e, "env_steps": 20 * e, "success_rate": 0.1 * seed, "steps_per_sec": 100.0}
        | {"count1_pct": COUNT1[seed] if counting else 0.0, "table_size": 50 if counting else 0}
        | {"bonus_mean": 0.4 if counting else (0.8 if arm == "control" else 0.0)}
        | {"bonus_std": 0.1 if counting else 0.0}
        | {"sampled_count1_pct": 60.0 if counting else 0.0}
        for e in (4, 8)
    ]


@pytest.fixture(scope="module")
def curves(tmp_path_factory):
    data = tmp_path_factory.mktemp("api")
    with ApiServer(Settings(port=0, data_dir=data, connect=["tcp/127.0.0.1:1"])) as server:
        body = {**TINY, "seeds": [0, 1, 2], "arms": ARMS, "name": "three arms"}
        exp = httpx.post(f"{server.url}/experiments", json=body).json()
        store = Store(server.settings.db_path)
        for run in exp["runs"]:
            store.add_points(run["id"], rows(run["arm"], run["seed"]))
        store.close()
        metrics = ["success_rate", "count1_pct", "sampled_count1_pct", "table_size"]
        r = httpx.get(f"{server.url}/experiments/{exp['id']}/curves", params={"metric": metrics})
        assert r.status_code == 200, r.text
        yield r.json()


def test_the_curves_of_an_arm_that_counts_nothing_have_no_count_metric(curves):
    for metric in ("count1_pct", "sampled_count1_pct", "table_size"):
        by_arm = {c["name"]: c for c in curves["metrics"][metric]}
        assert list(by_arm) == ["counting", "control", "no bonus"], "every arm keeps its place"
        assert by_arm["counting"]["episode"] == [4, 8], metric
        assert by_arm["control"]["episode"] == by_arm["no bonus"]["episode"] == [], metric
        assert by_arm["control"]["mean"] == by_arm["no bonus"]["mean"] == [], metric
    count1 = curves["metrics"]["count1_pct"][0]
    assert count1["mean"] == pytest.approx([80.0, 80.0])
    assert count1["hi"][0] == pytest.approx(80 + math.sqrt(800))  # over 100: the band
    success = {c["name"]: c["episode"] for c in curves["metrics"]["success_rate"]}
    assert success == {"counting": [4, 8], "control": [4, 8], "no bonus": [4, 8]}
    explore = {c["name"]: c["explore"] for c in curves["metrics"]["success_rate"]}
    assert explore == {"counting": "cen-macb", "control": "constant", "no bonus": "none"}


def test_the_png_draws_count1_of_the_counting_arm_only_on_a_0_to_100_axis(curves):
    fig = draw_curves(curves, "count1_pct")
    assert figure_legend(fig) == ["counting (3 seeds)"]
    low, high = fig.axes[0].get_ylim()
    assert -2 <= low <= 0 and 100 <= high <= 102, (low, high)
    success = draw_curves(curves, "success_rate")
    assert len(figure_legend(success)) == 3


def test_a_table_figure_gives_no_count1_for_the_arms_that_count_nothing():
    """Table 2's "no bonus" and control rows: the thesis gives none ("47%, -"), and the
    measured column says none either, rather than the 0% their rows carry."""
    fig = FIGURES["table2"]
    shapes = {x.name: (5000, 0.5) for x in fig.arms}  # count-1 50% in every row
    a = analysis.analyse(fig, *synthetic(fig, shapes, 40000, step=200))
    md = render.markdown(a, "mpe2")

    def measured(arm: str) -> str:
        arms = md[md.index("## Arms") : md.index("## Claims")]
        (row,) = [line for line in arms.splitlines() if line.startswith(f"| {arm} |")]
        return row.split(" | ")[4].removesuffix(" |")

    assert re.fullmatch(r"\d+%, 50%", measured("beta=0.8,k=512"))
    assert re.fullmatch(r"\d+%, -", measured("beta=0.0")), "explore none"
    assert re.fullmatch(r"\d+%, -", measured("constant beta=0.8 (control)"))
    png, _ = plot.draw(a, "mpe2")
    cells = [t.get_text() for t in png.axes[0].texts]
    controls = [c for c in cells if c.endswith("(thesis none: control)")]
    assert len(controls) == 4 and all(re.fullmatch(r"\d+%\n.*", c) for c in controls)
    assert sum(bool(re.match(r"\d+%, 50%\n", c)) for c in cells) == 16


def test_the_trainer_says_the_constant_arm_shifts_by_design_not_that_counting_waits(caplog):
    base = {"task": "speaker_listener", "algo": "cen-maddpg", "episodes": 15, "eval_every": 5}
    base |= NETS
    with caplog.at_level(logging.INFO, logger="macb.trainer"):
        rows = train(
            make_config({**base, "explore": "constant", "beta": 0.3}), None, progress=False
        )
    assert rows[-1]["bonus_std"] == 0 and rows[-1]["bonus_mean"] == pytest.approx(0.3)
    text = caplog.text
    assert "counting has not changed" not in text
    assert "constant shift by design (0.3 on every reward): the constant arm counts nothing" in text
    warned = [r for r in caplog.records if r.name == "macb.trainer" and r.levelno > logging.INFO]
    assert warned == []
