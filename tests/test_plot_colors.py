"""One arm, one colour: the PNGs (the API's plot, the reproduce figure) and the pages
(the dashboard, the figure view) colour an arm alike, from matplotlib's tab10 (tab20
beyond 10 arms), by the arm's place in its experiment, whichever arms a chart draws."""

from __future__ import annotations

import re
from pathlib import Path

from fastapi.testclient import TestClient
from matplotlib import colormaps
from matplotlib.colors import to_hex

from cli.reproduce.plot import draw
from cli.view import folder_view
from cli.view_app import page_app
from services.api.plot import TAB10, TAB20, arm_colors, arm_order, draw_curves, palette
from tests.test_view import _args, _report, _write

CHARTS_JS = Path(__file__).parent.parent / "services" / "api" / "charts.js"


def _js_list(name: str) -> tuple[str, ...]:
    body = re.search(rf"const {name} = \[(.*?)\];", CHARTS_JS.read_text(), re.S)
    assert body is not None, name
    return tuple(re.findall(r'"(#[0-9a-f]{6})"', body.group(1)))


def test_the_palettes_are_matplotlibs_in_python_and_in_the_pages_script():
    for name, ours in (("tab10", TAB10), ("tab20", TAB20)):
        cmap = colormaps[name]
        assert ours == tuple(to_hex(cmap(i)) for i in range(cmap.N))
    assert (_js_list("TAB10"), _js_list("TAB20")) == (TAB10, TAB20)
    assert palette(3) == list(TAB10[:3]) and palette(12)[:3] == list(TAB20[:3])


def _group(name: str, episodes: list[int]) -> dict:
    n = len(episodes)
    return {"name": name, "runs": ["r"], "episode": episodes, "mean": [0.5] * n,
            "lo": [0.4] * n, "hi": [0.6] * n}  # fmt: skip


def test_an_arm_keeps_its_colour_in_a_metric_that_some_arms_lack():
    """count-1 % has only the counting arms: the second arm of the experiment keeps its
    success-rate colour there (by index within the chart it took the first's)."""
    curves = {
        "name": "e",
        "metrics": {
            "success_rate": [_group(n, [4, 8]) for n in ("no bonus", "counting", "control")],
            "count1_pct": [_group("counting", [4, 8])],
        },
    }
    assert arm_order(curves) == ["no bonus", "counting", "control"]
    colors = arm_colors(arm_order(curves))
    drawn = {
        metric: {line.get_label().rsplit(" (", 1)[0]: to_hex(line.get_color())
                 for line in draw_curves(curves, metric).axes[0].get_lines()}
        for metric in ("success_rate", "count1_pct")
    }  # fmt: skip
    assert drawn["success_rate"] == colors
    assert drawn["count1_pct"] == {"counting": colors["counting"]} == {"counting": TAB10[1]}


def test_the_figure_view_sends_each_arm_the_colour_the_png_draws_it_in(tmp_path):
    """fig8's sparse arms with points, its dense arms with none."""
    _write(tmp_path, cut=1200)
    data = TestClient(page_app(folder_view(_args(tmp_path)))).get("/figure.json").json()
    a, _ = _report(tmp_path)
    fig, _ = draw(a, "thesis")
    png = {}
    for line in fig.axes[0].get_lines():
        name = line.get_label().rsplit(" (", 1)[0]
        if not name.startswith("_") and line.get_linestyle() in ("-", "--"):
            png.setdefault(name, to_hex(line.get_color()))
    sent = {arm["name"]: arm["color"] for arm in data["arms"] if arm["runs"]}
    drawn = [arm["name"] for arm in data["arms"] if arm["episode"]]
    assert drawn and set(png) == set(drawn) and all(png[n] == sent[n] for n in drawn), (sent, png)
    # each arm the experiment runs has its place, points or not: the colours its
    # dashboard gives them, in order; the arms it does not run (fig8's dense) have none
    assert list(sent.values()) == palette(len(sent))
    assert all(arm["color"] is None for arm in data["arms"] if not arm["runs"])


def test_an_arm_without_points_yet_keeps_its_place_in_the_palette(tmp_path):
    """An arm that has not started (queued, or failed at once) does not move the others'
    colours: they stay what the dashboard shows."""
    _write(tmp_path, cut=1200)
    for seed in (0, 1):
        (tmp_path / "runs" / f"Sparse-s{seed}" / "metrics.jsonl").write_text("")
    data = TestClient(page_app(folder_view(_args(tmp_path)))).get("/figure.json").json()
    colors = {arm["name"]: arm["color"] for arm in data["arms"] if arm["runs"]}
    assert not next(a for a in data["arms"] if a["name"] == "Sparse")["episode"]
    assert list(colors)[0] == "Sparse" and list(colors.values()) == palette(len(colors))
