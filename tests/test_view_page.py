"""The figure view in headless Chromium, as a user uses it: `macb view RUNS_DIR` on a runs
folder while rows are appended to it (real rows of a finished `macb run --local`, copied
a point at a time), and the API's /view?experiment=ID while a real run goes through the
cluster. The page must draw a new point when one arrives, hide and show an arm from its
legend, draw each seed on demand, and draw the values the report computes for the same
rows (cli/reproduce/analysis.py; the page writes each value to 6 significant digits).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import httpx
import numpy as np
import pytest

from cli.reproduce.analysis import analyse, claim_verdicts, columns
from cli.supervisor import free_port
from cli.view import runs_figure
from shared import procs
from tests.cdp import CHROMIUM, Browser
from tests.harness import TINY, Cluster, macb, spawn, wait_for, write_config

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(),
    reason="needs Debian's chromium at /usr/bin/chromium (apt-get install -y chromium; "
    ".ci/run installs it)",
)
TWO_ARMS = {
    "task": "simple",
    "algo": "ddpg",
    "reward": "dense",
    "episodes": 16,
    "eval_every": 2,
    "eval_episodes": 2,
    "hidden": [32, 32],
    "batch_size": 16,
    "learning_starts": 30,
    "learner_lanes": 1,
    "beta": 0.8,
    "k": 16,
    "arms": [
        {"name": "counting", "explore": "dis-macb"},
        {"name": "control", "explore": "constant"},
    ],
}
DRAWN = (
    "Object.fromEntries([...document.querySelectorAll('#main-chart path.curve-mean')]"
    ".map(p => [p.dataset.label, [p.dataset.episodes.split(',').map(Number),"
    " p.dataset.values.split(',').map(Number)]]))"
)


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """Two arms (counting and its constant control) x two seeds, run by `macb run --local`."""
    tmp = tmp_path_factory.mktemp("view-runs")
    config = write_config(tmp / "two-arms.yaml", TWO_ARMS)
    macb("run", str(config), "--local", "--seeds", "0", "1", "--out", str(tmp / "out"), "--quiet",
         check=True, timeout=600)  # fmt: skip
    return tmp / "out"


def _copy(finished: Path, live: Path, points: int) -> None:
    """The finished runs' config and first `points` rows, as if they were running."""
    for run in sorted(p for p in finished.iterdir() if (p / "metrics.jsonl").exists()):
        (live / run.name).mkdir(parents=True, exist_ok=True)
        shutil.copy(run / "config.json", live / run.name / "config.json")
        rows = (run / "metrics.jsonl").read_text().splitlines(keepends=True)
        (live / run.name / "metrics.jsonl").write_text("".join(rows[:points]))


def _report(live: Path) -> dict[str, tuple[list[int], np.ndarray, np.ndarray]]:
    """Per arm, what the report computes from the folder's rows: episodes, the smoothed
    mean over seeds, and each seed's smoothed curve."""
    runs, points = [], {}
    for run in sorted(p for p in live.iterdir() if p.is_dir()):
        config = json.loads((run / "config.json").read_text())
        runs.append({"id": run.name, "arm": run.name.rsplit("-s", 1)[0], "seed": config["seed"]})
        runs[-1]["config"] = config
        rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
        points[run.name] = columns(rows)
    exp = {"id": "x", "name": live.name, "seeds": [0, 1], "runs": runs}
    a = analyse(runs_figure(live.name, runs), exp, points)
    return {
        n: (arm.episodes.tolist(), arm.curve(), arm.smoothed["success_rate"])
        for n, arm in a.arms.items()
    }


def _six(values) -> list[float]:
    return [float(f"{v:.6g}") for v in values]


def test_macb_view_follows_a_folder_being_written_toggles_arms_and_draws_the_reports_values(
    finished, tmp_path
):
    live = tmp_path / "live"
    _copy(finished, live, 3)
    port = free_port()
    view = spawn("view", str(live), "--port", str(port), log=tmp_path / "view.log")
    url = f"http://127.0.0.1:{port}/"
    try:
        wait_for(lambda: _answers(url), timeout=60, interval=0.3, what="macb view answering")
        with Browser(tmp_path / "chromium") as page:
            page.goto(url)
            page.wait("document.body.dataset.ready === '1'", what="the page drew its data")
            drawn = page.js(DRAWN)
            assert sorted(drawn) == ["control", "counting"]
            assert drawn["counting"][0] == [2, 4, 6]
            version = page.js("document.body.dataset.version")

            _copy(finished, live, 4)  # a row more for every run
            _read_all(page, url, version)
            drawn = page.js(DRAWN)
            report = _report(live)
            for arm, (episodes, mean, _) in report.items():
                assert drawn[arm][0] == episodes == [2, 4, 6, 8], arm
                assert drawn[arm][1] == _six(mean), arm
            pair = page.js(
                "[...document.querySelectorAll('[data-pair] path.curve-mean')]"
                ".map(p => [p.closest('[data-pair]').dataset.pair, p.dataset.label])"
            )
            assert pair == [["counting", "counting"], ["counting", "control"]]

            page.click('input.arm-toggle[data-arm="control"]')
            page.wait("!document.querySelector('#main-chart path.curve-mean[data-label=control]')")
            assert sorted(page.js(DRAWN)) == ["counting"]
            page.click('input.arm-toggle[data-arm="control"]')
            page.wait(
                "document.querySelector('#main-chart path.curve-mean[data-label=control]') !== null"
            )
            assert sorted(page.js(DRAWN)) == ["control", "counting"]

            page.click("#seeds-toggle")
            seeds = page.wait(
                "[...document.querySelectorAll('#main-chart path.curve-seed')].map(p =>"
                " [p.dataset.label, +p.dataset.seed, p.dataset.values.split(',').map(Number)])"
            )
            for arm, seed, values in seeds:
                assert values == _six(report[arm][2][seed]), (arm, seed)
            assert len(seeds) == 4

            version = page.js("document.body.dataset.version")
            _copy(finished, live, 8)  # the rest: the runs' ends
            _read_all(page, url, version)
            assert page.js("document.querySelector('tr.run').dataset.episode") == "16"
            assert page.js("document.getElementById('progress-line').textContent").startswith(
                "complete"
            )
            page.screenshot(tmp_path / "view.png")
    finally:
        procs.end(view, 5, group=True)
    print(f"screenshot: {tmp_path / 'view.png'}")


def _read_all(page: Browser, url: str, before: str) -> None:
    """Wait until the page has drawn the folder as it is now, every run's file written.
    A poll between two of `_copy`'s files gives a new version with some runs' rows
    only; the server's version of the whole folder is the one to wait for."""
    now = httpx.get(url + "figure.json", timeout=10).headers["ETag"]
    assert now != before, "the server did not see the new rows"
    page.wait(f"document.body.dataset.version === {json.dumps(now)}", what="the new rows read")


def _answers(url: str) -> bool:
    try:
        return httpx.get(url + "figure.json", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def _healthy(url: str) -> bool:
    try:
        return httpx.get(f"{url}/health", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def test_the_dashboards_figure_view_follows_a_run_through_the_api(tmp_path):
    """A real run on the cluster: from the dashboard's link, the figure view draws its
    points as the event stream brings them, the values the report computes from the
    stored points. Eight arms on one learner: one runs, seven wait, and the page must
    not hold the browser's six connections to the API with their runs' streams."""
    # Far longer than the test waits: the test stops it after two draws, so however fast
    # the machine, the run is still going when the page first draws it.
    arms = [{"name": f"beta {b}", "beta": b} for b in (0.8, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)]
    body = {**TINY, "episodes": 4000, "eval_every": 4, "seeds": [0], "name": "figure view"}
    body["arms"] = arms
    (tmp_path / "cluster").mkdir()
    env = {"MACB_PEER_GRACE_S": "8"}
    with Cluster(tmp_path / "cluster", env=env) as cluster, Browser(tmp_path / "chromium") as page:
        # The page is open before any service is, so it follows the run from its start.
        cluster.router()
        cluster.api(answering=None)
        url = cluster.url
        wait_for(lambda: _healthy(url), timeout=60, interval=0.3, what="the API answering")
        exp = httpx.post(f"{url}/experiments", json=body).json()
        page.goto(f"{url}/")
        link = page.wait(
            f"document.querySelector('a.figure-link[data-experiment=\"{exp['id']}\"]')?.href"
        )
        page.goto(link)
        page.wait("document.body.dataset.ready === '1'", what="the figure view drew")
        cluster.services(actors=1)
        first = page.wait(
            "(document.querySelector('#main-chart path.curve-mean') || {dataset: {}})"
            ".dataset.episodes",
            timeout=180,
            what="a first point drawn",
        )
        page.wait(
            "document.querySelector('#main-chart path.curve-mean').dataset.episodes"
            f" !== {json.dumps(first)}",
            timeout=180,
            what="a new point drawn",
        )
        assert not first.endswith(",4000")
        httpx.post(f"{url}/experiments/{exp['id']}/stop").raise_for_status()
        wait_for(
            lambda: httpx.get(f"{url}/experiments/{exp['id']}").json()["status"] == "stopped",
            timeout=120,
            interval=0.5,
            what="the run stopped",
        )

        def analysed():
            done = httpx.get(f"{url}/experiments/{exp['id']}").json()
            (run,) = [r for r in done["runs"] if r["points"]]  # the one that ran
            points = httpx.get(f"{url}/runs/{run['id']}/metrics").json()["points"]
            figure = analyse(runs_figure(done["name"], [run]), done, {run["id"]: columns(points)})
            return run, figure.arm(run["arm"])

        def drawn_all() -> tuple | None:
            run, arm = analysed()
            drawn = page.js(DRAWN).get(run["arm"])
            return (drawn, arm) if drawn is not None and drawn[0] == arm.episodes.tolist() else None

        # Compared with what is stored each time: a point in flight at the stop may land,
        # so the values are checked against the same reading of the store.
        drawn, arm = wait_for(drawn_all, timeout=30, interval=0.5, what="every stored point drawn")
        assert drawn[1] == _six(arm.curve())
        page.screenshot(tmp_path / "api-view.png")


@pytest.mark.slow
def test_macb_view_of_a_reproduce_local_campaign_while_it_trains(tmp_path):
    """`macb reproduce fig8 --local` (its sparse arms, two seeds, cut short) training into
    a folder while `macb view --figure fig8` with the same flags serves it: the page
    draws points as they come, says every claim is "not run to that length", and at the
    end draws the values the report computes from the folder."""
    flags = ["--profile", "thesis", "--arms", "sparse*", "--seeds", "0", "1", "--episodes", "12"]
    out = tmp_path / "fig8"
    port = free_port()
    train = spawn("reproduce", "fig8", "--local", *flags, "--out", str(out), "--quiet",
                  log=tmp_path / "reproduce.log")  # fmt: skip
    view = None
    try:
        wait_for(lambda: (out / "runs").is_dir(), timeout=120, interval=0.3, what="runs/")
        view = spawn("view", str(out), "--figure", "fig8", *flags, "--port", str(port),
                     log=tmp_path / "view.log")  # fmt: skip
        url = f"http://127.0.0.1:{port}/"
        wait_for(lambda: _answers(url), timeout=60, interval=0.3, what="macb view answering")
        with Browser(tmp_path / "chromium") as page:
            page.goto(url)
            page.wait("document.body.dataset.ready === '1'", what="the page drew its data")
            first = page.wait(
                "(document.querySelector('#main-chart path.curve-mean') || {dataset: {}})"
                ".dataset.episodes",
                timeout=300,
                what="a first point drawn",
            )
            page.wait(
                "document.querySelector('#main-chart path.curve-mean').dataset.episodes"
                f" !== {json.dumps(first)}",
                timeout=300,
                what="a new point drawn",
            )
            verdicts = page.js(
                "[...document.querySelectorAll('tr.claim')].map(r => r.dataset.verdict)"
            )
            assert verdicts and set(verdicts) == {"not run to that length"}
            assert train.wait(timeout=900) in (0, 1)  # 1: the page says the runs are short
            page.wait("document.getElementById('progress-line').textContent"
                      ".startsWith('complete')", timeout=30)  # fmt: skip
            drawn = page.js(DRAWN)
        data = httpx.get(url + "figure.json").json()
    finally:
        procs.end(train, 5, group=True)
        if view is not None:
            procs.end(view, 5, group=True)
    from cli.local import expand_body, local_experiment, local_points
    from cli.reproduce.experiments import experiment_body, select_arms
    from cli.reproduce.figures import FIGURES

    fig = FIGURES["fig8"]
    body = select_arms(fig, experiment_body(fig, "thesis", [0, 1], 12), ["sparse*"])
    name, seeds, runs = expand_body(body)
    exp = local_experiment(name, seeds, runs, out / "runs")
    points = {k: columns(v) for k, v in local_points(runs, out / "runs").items()}
    a = analyse(fig, exp, points)
    assert sorted(drawn) == sorted(n for n, arm in a.arms.items() if len(arm.episodes))
    for name, (episodes, values) in drawn.items():
        assert episodes == a.arm(name).episodes.tolist() and episodes[-1] == 12
        assert values == _six(a.arm(name).curve()), name
    claims = [c["verdict"] for c in data["claims"]]
    assert claims == [v for *_, v in claim_verdicts(a)]


def test_the_page_marks_the_thesis_values_beside_their_arms_and_hides_them_with_them(tmp_path):
    """fig8's sparse arms started for 40,000 episodes, 1,200 run: the main chart marks
    the three values the claims state (at 40,000, 40,000 and 15,000), each in its arm's
    colour; hiding an arm hides its mark, and the arm's pair chart keeps it."""
    from tests.test_view import _write

    _write(tmp_path, cut=1200)
    port = free_port()
    view = spawn("view", str(tmp_path), "--figure", "fig8", "--profile", "thesis", "--arms",
                 "sparse*", "--seeds", "0", "1", "--port", str(port),
                 log=tmp_path / "view.log")  # fmt: skip
    marks = (
        "[...document.querySelectorAll('#main-chart g.thesis-mark')].map(g => [g.dataset.claim,"
        " g.dataset.arm, +g.dataset.episode, g.querySelector('polygon').getAttribute('stroke')])"
    )
    try:
        url = f"http://127.0.0.1:{port}/"
        wait_for(lambda: _answers(url), timeout=60, interval=0.3, what="macb view answering")
        with Browser(tmp_path / "chromium") as page:
            page.goto(url)
            page.wait("document.body.dataset.ready === '1'", what="the page drew its data")
            drawn = page.js(marks)
            colors = page.js(
                "Object.fromEntries([...document.querySelectorAll('#main-chart path.curve-mean')]"
                ".map(p => [p.dataset.label, p.getAttribute('stroke')]))"
            )
            assert [d[:3] for d in drawn] == [
                ["1", "Sparse", 40000],
                ["2", "Sparse + Dis-MACB", 40000],
                ["3", "Sparse + Cen-MACB", 15000],
            ]
            assert all(stroke == colors[arm] for _, arm, _, stroke in drawn)
            assert "Hollow diamonds" in page.js("document.getElementById('how').textContent")
            page.js(
                "document.querySelector('input.arm-toggle[data-arm=\"Sparse + Cen-MACB\"]').click()"
            )
            assert [d[0] for d in page.js(marks)] == ["1", "2"]
            pair = page.js(
                "[...document.querySelectorAll('[data-pair=\"Sparse + Dis-MACB\"] g.thesis-mark')]"
                ".map(g => g.dataset.claim)"
            )
            assert pair == ["2"]
    finally:
        procs.end(view, 5, group=True)
