"""The dashboard in headless Chromium against a running API with real metrics.

A real cluster runs an experiment (two seeds x two grid points); Chromium loads
GET /, lets the page fetch and draw, and dumps the DOM. The curves it drew must
be the mean over seeds of the points the API stored, per episode, for the success
rate, the count-1 percentage and the throughput; a screenshot is saved in the
test's output folder (tmp_path). An experiment with named arms (its points written
into the store, as the scheduler writes them) must come out overlaid on each chart,
one curve per arm, with every arm's name in the legend.
"""

from __future__ import annotations

import subprocess
from html.parser import HTMLParser
from pathlib import Path

import httpx
import pytest

from services.api.main import ApiServer, Settings
from services.api.store import Store
from tests.cdp import CHROMIUM, HEADLESS_FLAGS, Browser
from tests.conftest import wait_for
from tests.test_api_e2e import TINY, api_cluster

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(),
    reason="needs Debian's chromium at /usr/bin/chromium (apt-get install -y chromium; "
    ".ci/run installs it)",
)
CHARTS = ("success_rate", "count1_pct", "steps_per_sec")


def chromium(url: str, out: Path, *action: str, budget_ms: int = 8000) -> str:
    out.mkdir(parents=True, exist_ok=True)
    cmd = [
        str(CHROMIUM),
        *HEADLESS_FLAGS,
        f"--user-data-dir={out / 'chromium-profile'}",
        f"--virtual-time-budget={budget_ms}",
        "--window-size=1400,1800",
        *action,
        url,
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


VOID = {"meta", "link", "br", "img", "input", "hr", "col", "wbr", "source"}


class Dom(HTMLParser):
    """Every element's tag and attributes, in document order; `#text` is the text
    inside it (its children's included)."""

    def __init__(self, html: str) -> None:
        super().__init__()
        self.elements: list[tuple[str, dict[str, str]]] = []
        self._open: list[tuple[str, dict[str, str]]] = []
        self.feed(html)

    def handle_starttag(self, tag, attrs):
        element = (tag, {**{k: v or "" for k, v in attrs}, "#text": ""})
        self.elements.append(element)
        if tag not in VOID:
            self._open.append(element)

    def handle_endtag(self, tag):
        while self._open:
            if self._open.pop()[0] == tag:
                break

    def handle_data(self, data):
        for _, attrs in self._open:
            attrs["#text"] += data

    def find(self, tag: str, **attrs: str) -> list[dict[str, str]]:
        want = {k.rstrip("_").replace("_", "-"): v for k, v in attrs.items()}
        return [
            a
            for t, a in self.elements
            if t == tag
            and all(
                a.get(k) == v or (k == "class" and v in a.get(k, "").split())
                for k, v in want.items()
            )
        ]


@pytest.fixture(scope="module")
def finished_experiment(tmp_path_factory):
    with api_cluster(tmp_path_factory.mktemp("dashboard")) as cluster:
        url = cluster.url
        body = {**TINY, "seeds": [0, 1], "grid": {"k": [32, 64]}, "name": "dashboard check"}
        exp = httpx.post(f"{url}/experiments", json=body).json()
        wait_for(
            lambda: httpx.get(f"{url}/experiments/{exp['id']}").json()["status"] == "completed",
            timeout=180,
            interval=0.5,
            what="experiment completed",
        )
        yield url, httpx.get(f"{url}/experiments/{exp['id']}").json()


def test_dashboard_draws_the_stored_learning_curves(finished_experiment, tmp_path):
    url, exp = finished_experiment
    points = {
        r["id"]: httpx.get(f"{url}/runs/{r['id']}/metrics").json()["points"] for r in exp["runs"]
    }
    dom = Dom(chromium(f"{url}/", tmp_path, "--dump-dom"))
    body = dom.find("body")[0]
    assert body["data-ready"] == "1"
    assert int(body["data-updates"]) >= 2, "the page keeps refreshing itself"
    (card,) = dom.find("section", data_experiment=exp["id"])
    assert card["data-status"] == "completed"
    for run in exp["runs"]:
        (row,) = dom.find("tr", data_run=run["id"])
        assert row["data-status"] == "completed"
    for metric in CHARTS:
        curves = dom.find(
            "path", class_="curve-mean", data_experiment=exp["id"], data_metric=metric
        )
        assert sorted(c["data-label"] for c in curves) == ["k=32", "k=64"], metric
        for c in curves:
            k = int(c["data-label"].split("=")[1])
            runs = [r["id"] for r in exp["runs"] if r["point"] == {"k": k}]
            assert len(runs) == 2
            episodes = sorted({p["episode"] for r in runs for p in points[r]})
            assert episodes == [4, 8, 12]
            expected = [
                sum(p[metric] for r in runs for p in points[r] if p["episode"] == e) / len(runs)
                for e in episodes
            ]
            assert c["data-episodes"] == "4,8,12"
            assert c["data-seeds"] == "2,2,2"
            drawn = [float(v) for v in c["data-values"].split(",")]
            assert drawn == pytest.approx(expected, rel=1e-5, abs=1e-9), metric
            assert c["d"].count("L") == len(episodes) - 1 and c["d"].startswith("M")
        bands = [b for b in dom.find("polygon", class_="curve-band") if b["data-label"]]
        assert len(bands) >= 2 * len(CHARTS)
    shot = tmp_path / "dashboard.png"
    chromium(f"{url}/", tmp_path, f"--screenshot={shot}")
    assert shot.stat().st_size > 20_000
    print(f"screenshot: {shot}")


def test_dashboard_overlays_an_experiments_arms_with_their_names_in_the_legend(tmp_path):
    arms = [
        {"name": "Cen-MACB", "explore": "cen-macb"},
        {"name": "Dis-MACB", "explore": "dis-macb"},
    ]
    server = ApiServer(
        Settings(port=0, data_dir=tmp_path / "api", connect=["tcp/127.0.0.1:1"])  # no bus
    ).start()
    try:
        body = {**TINY, "seeds": [0, 1], "arms": arms, "name": "two arms"}
        exp = httpx.post(f"{server.url}/experiments", json=body).json()
        store = Store(server.settings.db_path)
        values = {("Cen-MACB", 0): (0.2, 0.6), ("Cen-MACB", 1): (0.4, 1.0)}
        values |= {("Dis-MACB", 0): (0.0, 0.1), ("Dis-MACB", 1): (0.1, 0.2)}
        for run in exp["runs"]:
            rows = [
                {"episode": e, "env_steps": 20 * e, "success_rate": v, "count1_pct": 5.0 * e}
                | {"count1_pct": 5.0 * e + (30 if run["arm"] == "Dis-MACB" else 0)}
                | {"steps_per_sec": 100.0 + 10 * run["seed"]}
                for e, v in zip((4, 8), values[(run["arm"], run["seed"])], strict=True)
            ]
            store.add_points(run["id"], rows)
        store.close()
        dom = Dom(chromium(f"{server.url}/", tmp_path, "--dump-dom"))
        shot = tmp_path / "arms.png"
        chromium(f"{server.url}/", tmp_path, f"--screenshot={shot}")
    finally:
        server.stop()
    assert dom.find("body")[0]["data-ready"] == "1"
    (card,) = dom.find("section", data_experiment=exp["id"])
    legend = dom.find("span", class_="legend-item")
    assert [x["data-arm"] for x in legend] == ["Cen-MACB", "Dis-MACB"]
    assert [x["#text"] for x in legend] == ["Cen-MACB (2 seeds)", "Dis-MACB (2 seeds)"]
    for metric in CHARTS:
        curves = dom.find(
            "path", class_="curve-mean", data_experiment=exp["id"], data_metric=metric
        )
        assert [c["data-label"] for c in curves] == ["Cen-MACB", "Dis-MACB"], metric
        assert len({c["stroke"] for c in curves}) == 2, "each arm its own colour"
        assert all(c["data-seeds"] == "2,2" for c in curves)
    success = {
        c["data-label"]: [float(v) for v in c["data-values"].split(",")]
        for c in dom.find("path", class_="curve-mean", data_metric="success_rate")
    }
    assert success["Cen-MACB"] == pytest.approx([0.3, 0.8])
    assert success["Dis-MACB"] == pytest.approx([0.05, 0.15])
    count1 = {
        c["data-label"]: [float(v) for v in c["data-values"].split(",")]
        for c in dom.find("path", class_="curve-mean", data_metric="count1_pct")
    }
    assert count1 == {"Cen-MACB": [20.0, 40.0], "Dis-MACB": [50.0, 70.0]}
    bands = dom.find("polygon", class_="curve-band")
    assert sorted(b["data-label"] for b in bands) == sorted(["Cen-MACB", "Dis-MACB"] * len(CHARTS))
    cells = {r["id"]: dom.find("tr", data_run=r["id"]) for r in exp["runs"]}
    assert all(len(v) == 1 for v in cells.values())
    assert [c["#text"] for c in dom.find("td", class_="arm")] == [r["arm"] for r in exp["runs"]]
    assert shot.stat().st_size > 20_000
    print(f"screenshot: {shot}")


def test_dashboard_draws_the_bonus_and_says_when_it_is_a_constant_shift(tmp_path):
    """The bonus diagnostics are charted per arm; an arm whose bonus had std 0 at its
    last points (every key new, or the constant arm) gets a note saying so, the other
    arm none."""
    arms = [{"name": "counting", "explore": "cen-macb"}, {"name": "shifted", "explore": "constant"}]
    server = ApiServer(
        Settings(port=0, data_dir=tmp_path / "api", connect=["tcp/127.0.0.1:1"])  # no bus
    ).start()
    try:
        body = {**TINY, "seeds": [0, 1], "arms": arms, "name": "bonus check"}
        exp = httpx.post(f"{server.url}/experiments", json=body).json()
        store = Store(server.settings.db_path)
        for run in exp["runs"]:
            counting = run["arm"] == "counting"
            rows = [
                {"episode": e, "env_steps": 20 * e, "success_rate": 0.0, "count1_pct": 50.0}
                | {"steps_per_sec": 100.0, "bonus_mean": 0.5 if counting else 0.8}
                | {"bonus_std": 0.1 if counting else 0.0}
                | {"sampled_count1_pct": 60.0 - 10 * run["seed"] if counting else 0.0}
                for e in (4, 8, 12)
            ]
            store.add_points(run["id"], rows)
        store.close()
        dom = Dom(chromium(f"{server.url}/", tmp_path, "--dump-dom"))
    finally:
        server.stop()
    notes = dom.find("div", class_="shift-note")
    assert [n["data-arm"] for n in notes] == ["shifted"]
    assert "constant shift" in notes[0]["#text"]
    drawn = {
        (c["data-metric"], c["data-label"]): [float(v) for v in c["data-values"].split(",")]
        for c in dom.find("path", class_="curve-mean", data_experiment=exp["id"])
    }
    assert drawn[("bonus_mean", "counting")] == pytest.approx([0.5] * 3)
    assert drawn[("bonus_mean", "shifted")] == pytest.approx([0.8] * 3)
    assert drawn[("sampled_count1_pct", "counting")] == pytest.approx([55.0] * 3)


def test_count1_charts_run_0_to_100_and_leave_out_the_arms_that_count_nothing(tmp_path):
    """A percentage axis runs 0-100 however far a band reaches (seeds at 100, 100 and 40
    give mean + std 108: the axis went to 200). The control (explore: constant) and the
    no-bonus arm count nothing, so they have no count-1 curve (their rows' 0s are no
    measurement); the control's note says what it is, not that counting waits."""
    arms = [
        {"name": "counting", "explore": "cen-macb"},
        {"name": "control", "explore": "constant"},
        {"name": "no bonus", "explore": "none"},
    ]
    server = ApiServer(
        Settings(port=0, data_dir=tmp_path / "api", connect=["tcp/127.0.0.1:1"])  # no bus
    ).start()
    try:
        body = {**TINY, "seeds": [0, 1, 2], "arms": arms, "name": "count-1 check"}
        exp = httpx.post(f"{server.url}/experiments", json=body).json()
        store = Store(server.settings.db_path)
        for run in exp["runs"]:
            counting = run["arm"] == "counting"
            bonus = {"counting": 0.4, "control": 0.8, "no bonus": 0.0}[run["arm"]]
            rows = [
                {"episode": e, "env_steps": 20 * e, "success_rate": 0.5, "steps_per_sec": 100.0}
                | {"count1_pct": (100.0, 100.0, 40.0)[run["seed"]] if counting else 0.0}
                | {"sampled_count1_pct": 60.0 if counting else 0.0}
                | {"bonus_mean": bonus, "bonus_std": 0.1 if counting else 0.0}
                for e in (4, 8, 12)
            ]
            store.add_points(run["id"], rows)
        store.close()
        with Browser(tmp_path / "chromium") as page:
            page.goto(f"{server.url}/")
            page.wait("document.body.dataset.ready === '1'")
            card = f'section[data-experiment="{exp["id"]}"]'
            ticks = page.js(
                f'[...document.querySelectorAll(\'{card} svg[data-metric="count1_pct"] '
                'g.axes text[text-anchor="end"]\')].map(t => t.textContent)'
            )
            drawn = page.js(
                f"[...document.querySelectorAll('{card} path.curve-mean')]"
                ".map(p => [p.dataset.metric, p.dataset.label, p.getAttribute('stroke')])"
            )
            notes = page.js(
                "[...document.querySelectorAll('.shift-note')]"
                ".map(n => [n.dataset.arm, n.textContent])"
            )
            page.screenshot(tmp_path / "count1.png")
    finally:
        server.stop()
    assert ticks == ["0", "25", "50", "75", "100"]
    labels: dict[str, list[str]] = {}
    for metric, label, _ in drawn:
        labels.setdefault(metric, []).append(label)
    assert labels["success_rate"] == ["counting", "control", "no bonus"]
    assert labels["bonus_mean"] == ["counting", "control", "no bonus"]
    assert labels["count1_pct"] == labels["sampled_count1_pct"] == ["counting"]
    colour = {(m, a): c for m, a, c in drawn}
    assert colour[("count1_pct", "counting")] == colour[("success_rate", "counting")]
    ((arm, text),) = notes
    assert arm == "control" and "constant shift by design" in text
    assert "counts nothing (no count-1 curves)" in text
    assert "counting has not changed" not in text


def test_the_form_creates_an_experiment_that_runs_and_the_buttons_stop_it(tmp_path):
    """Through the page only, in headless Chromium driven over the DevTools protocol, on
    a real cluster: a bad body's 422 reasons show beside the fields they name and
    nothing is created; the form's experiment (a preset, seeds and a grid) runs, its
    run's stop button stops that run, the experiment's stops the rest."""
    (tmp_path / "cluster").mkdir()
    with api_cluster(tmp_path / "cluster") as cluster, Browser(tmp_path / "chromium") as page:
        url = cluster.url
        page.goto(f"{url}/")
        page.wait("document.getElementById('create-form').dataset.ready === '1'")
        page.choose("#f-preset", "default")  # configs/default.yaml
        keys = page.js("[...document.querySelectorAll('#f-rows input')].map(i => i.dataset.key)")
        assert keys == [
            "task",
            "algo",
            "explore",
            "beta",
            "k",
            "episodes",
            "eval_every",
            "interleave",
            "learner_lanes",
        ]
        assert page.js("document.getElementById('f-seeds').value") == "0"
        page.type('#f-rows input[data-key="beta"]', "1000")
        page.type("#f-grid", "gama=0.9,0.99")
        page.type("#f-seeds", "0 1")
        page.click("#f-submit")
        page.wait("document.getElementById('create-form').dataset.refused === '1'")
        beside = page.js(
            "Object.fromEntries([...document.querySelectorAll('.field-error')]"
            ".filter(e => e.textContent).map(e => [e.dataset.for, e.textContent]))"
        )
        assert beside == {
            "beta": "Input should be less than or equal to 100",
            "grid": "grid.gama: unknown key (misspelt?)",
        }
        invalid = "[...document.querySelectorAll('.invalid')].map(e => e.id)"
        assert sorted(page.js(invalid)) == ["f-grid", "f-key-beta"]
        assert httpx.get(f"{url}/experiments").json()["total"] == 0, "nothing was created"

        page.type('#f-rows input[data-key="beta"]', "0.8")
        page.type("#f-grid", "k=32,64")
        page.type('#f-rows input[data-key="episodes"]', "2000")  # runs until stopped
        page.type('#f-rows input[data-key="eval_every"]', "2")
        for key, value in [("eval_episodes", "2"), ("hidden", "[32, 32]"), ("batch_size", "16")]:
            page.choose("#f-add-key", key)
            page.click("#f-add")
            page.type(f'#f-rows input[data-key="{key}"]', value)
        page.type("#f-name", "from the form")
        page.click("#f-submit")
        exp_id = page.wait("document.getElementById('create-form').dataset.created")
        assert page.js(invalid) == [] and page.js(
            "[...document.querySelectorAll('.field-error')].every(e => !e.textContent)"
        )
        exp = httpx.get(f"{url}/experiments/{exp_id}").json()
        assert exp["name"] == "from the form" and exp["seeds"] == [0, 1]
        assert [(r["seed"], r["point"]) for r in exp["runs"]] == [
            (0, {"k": 32}),
            (1, {"k": 32}),
            (0, {"k": 64}),
            (1, {"k": 64}),
        ]
        config = exp["runs"][0]["config"]
        assert (config["task"], config["episodes"], config["hidden"]) == ("simple", 2000, [32, 32])
        first, second = (r["id"] for r in exp["runs"][:2])
        row = f"document.querySelector('tr[data-run=\"{first}\"]')"
        page.wait(
            f"{row} && {row}.dataset.status === 'running' && +{row}.dataset.points >= 2",
            timeout=120,
            what="the first run running, with points drawn",
        )
        page.screenshot(tmp_path / "running.png")
        page.click(f'button.stop-run[data-run="{first}"]')
        page.wait(f"{row}.dataset.status === 'stopped'", timeout=60, what="the run stopped")
        run = httpx.get(f"{url}/runs/{first}").json()
        assert run["status"] == "stopped" and run["reason"] == "stopped by user"
        nxt = f"document.querySelector('tr[data-run=\"{second}\"]').dataset.status"
        page.wait(f"{nxt} === 'running'", timeout=60, what="the next run started")
        card = f"document.querySelector('section[data-experiment=\"{exp_id}\"]')"
        page.click(f'button.stop-experiment[data-experiment="{exp_id}"]')
        page.wait(f"{card}.dataset.status === 'stopped'", timeout=60, what="experiment stopped")
        assert (
            page.js(f"{card}.querySelectorAll('button.stop-run, button.stop-experiment').length")
            == 0
        )
        page.screenshot(tmp_path / "stopped.png")
        exp = httpx.get(f"{url}/experiments/{exp_id}").json()
        assert [r["status"] for r in exp["runs"]] == ["stopped"] * 4
        assert exp["runs"][0]["points"] >= 2 and exp["runs"][3]["points"] == 0

        def free():
            workers = httpx.get(f"{url}/workers").json()["workers"]
            return all(w["run"] is None for w in workers)

        wait_for(free, timeout=30, what="every service free again")
    assert (tmp_path / "stopped.png").stat().st_size > 20_000
    print(f"screenshots: {tmp_path / 'running.png'}, {tmp_path / 'stopped.png'}")
