"""The figure view's data (cli/view.py) over plain HTTP: `macb view`'s /figure.json for a
runs folder and the API's /experiments/{id}/figure, each equal to what the report
(cli/reproduce/: analysis, claims, controls, status) and `macb.summary` compute for the
same rows, following rows as they are appended (ETag, 304 while none is). The page in
Chromium: tests/test_view_page.py.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

import macb
from cli.local import expand_body, local_experiment, local_points
from cli.reproduce.analysis import analyse, claim_verdicts, columns
from cli.reproduce.controls import control_verdicts
from cli.reproduce.experiments import experiment_body, experiment_name, select_arms
from cli.reproduce.figures import FIGURES
from cli.reproduce.status import read_folders
from cli.runs_folder import RunsError
from cli.view import FolderView, experiment_view, folder_view
from cli.view_app import page_app
from services.api.main import ApiServer, Settings
from services.api.store import Store
from shared.config import TrainConfig
from shared.net.messages import Assignment
from tests.harness import TINY
from tests.test_fig8_page import _rows

FIG8 = FIGURES["fig8"]


def _body() -> dict:
    return select_arms(FIG8, experiment_body(FIG8, "thesis", [0, 1], None), ["sparse*"])


def _write(out: Path, cut: int | None = None) -> None:
    """fig8's sparse arms, two seeds, as `--local` writes them (the first `cut` rows)."""
    _, _, runs = expand_body(_body())
    for r in runs:
        folder = out / "runs" / r.name
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "config.json").write_text(json.dumps(r.config.model_dump(mode="json")))
        lines = [json.dumps(row) + "\n" for row in _rows(r.arm or "", r.seed)[:cut]]
        (folder / "metrics.jsonl").write_text("".join(lines))


def _args(out: Path, **over) -> argparse.Namespace:
    base = {"runs_dir": str(out), "figure": "fig8", "profile": "thesis", "arms": ["sparse*"]}
    base |= {"seeds": [0, 1], "episodes": None, "precision": None}
    return argparse.Namespace(**(base | over))


def _report(out: Path):
    """What `macb reproduce fig8 --report-only` computes from the folder."""
    name, seeds, runs = expand_body(_body())
    exp = local_experiment(name, seeds, runs, out / "runs")
    points = {k: columns(v) for k, v in local_points(runs, out / "runs").items()}
    return analyse(FIG8, exp, points), read_folders(runs, out / "runs", FIG8.episodes)


def _nan(values: list) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def test_the_folders_figure_json_is_the_reports_and_follows_appended_rows(tmp_path):
    _write(tmp_path, cut=1200)
    client = TestClient(page_app(folder_view(_args(tmp_path))))
    got = client.get("/figure.json")
    assert got.status_code == 200
    data = got.json()
    a, progress = _report(tmp_path)
    assert [x["name"] for x in data["arms"]] == [arm.name for arm in FIG8.arms]
    for arm in data["arms"]:
        mine = a.arm(arm["name"])
        assert arm["episode"] == mine.episodes.tolist()
        if not arm["episode"]:
            continue
        low, high = mine.band()
        np.testing.assert_array_equal(_nan(arm["mean"]), mine.curve())
        np.testing.assert_array_equal(_nan(arm["low"]), low)
        np.testing.assert_array_equal(_nan(arm["high"]), high)
        for i, s in enumerate(arm["per_seed"]):
            assert s["seed"] == mine.seeds[i]
            np.testing.assert_array_equal(_nan(s["values"]), mine.smoothed[FIG8.metric][i])
        assert (arm["converged"], arm["window"]) == (mine.converged, mine.window)
    # the sparse arms' curves: 75% bands (fig8's), so the band is not mean +- std
    dis = a.arm("Sparse + Dis-MACB")
    assert not np.array_equal(dis.band()[0], dis.curve() - dis.std[FIG8.metric])
    assert [(c["claim"], c["measured"], c["verdict"]) for c in data["claims"]] == [
        (c.text, m, v) for c, m, v in claim_verdicts(a)
    ]
    assert {c["verdict"] for c in data["claims"]} == {"not run to that length"}
    # the values the report's plot marks (the runs were started for 40,000 episodes)
    assert [(m["claim"], m["arm"], m["episode"], m["lo"], m["hi"]) for m in data["marks"]] == [
        (1, "Sparse", 40000, 0.35, 0.55),
        (2, "Sparse + Dis-MACB", 40000, 0.6, 0.8),
        (3, "Sparse + Cen-MACB", 15000, 0.9, 1.0),
    ]
    assert [tuple(c.values()) for c in data["controls"]] == [tuple(c) for c in control_verdicts(a)]
    pairs = {x["name"]: x["control"] for x in data["arms"] if x["control"] and x["runs"]}
    assert pairs == {
        "Sparse + Dis-MACB": "Sparse + constant beta=0.8 (control)",
        "Sparse + Cen-MACB": "Sparse + constant beta=0.8 (control)",
    }
    assert data["progress"]["reached"] == progress.reached()
    assert [r["episode"] for r in data["progress"]["runs"]] == [r.episode for r in progress.runs]
    assert data["progress"]["finish"].startswith("projected finish")
    # the Python API says the same of the same rows
    s = macb.summary(macb.load_runs(tmp_path), "fig8")
    curve = s.curves[s.curves["arm"] == "Sparse + Dis-MACB"]
    dis_json = next(x for x in data["arms"] if x["name"] == "Sparse + Dis-MACB")
    np.testing.assert_array_equal(curve["mean"].to_numpy(), _nan(dis_json["mean"]))
    assert s.claims["verdict"].tolist() == [c["verdict"] for c in data["claims"]]

    etag = got.headers["etag"]
    assert client.get("/figure.json", headers={"If-None-Match": etag}).status_code == 304
    _write(tmp_path, cut=1300)  # rows appended: a new version, the new points in it
    again = client.get("/figure.json", headers={"If-None-Match": etag})
    assert again.status_code == 200 and again.headers["etag"] != etag
    lengths = {x["name"]: x["length"] for x in again.json()["arms"]}
    assert lengths["Sparse + Dis-MACB"] == 1300
    a, _ = _report(tmp_path)
    np.testing.assert_array_equal(
        _nan(next(x for x in again.json()["arms"] if x["name"] == "Sparse")["mean"]),
        a.arm("Sparse").curve(),
    )


def test_a_folder_of_any_runs_pairs_each_counting_run_with_its_constant_control(tmp_path):
    """No figure: the arms are the runs' folders (as macb.load_runs names them), the
    control the run whose config differs only in the keys counting reads."""
    base = {"task": "simple", "algo": "ddpg", "beta": 0.8, "episodes": 40, "seed": 0}
    for name, explore in (("counting", "dis-macb"), ("control", "constant"), ("plain", "none")):
        folder = tmp_path / name
        folder.mkdir()
        config = TrainConfig.model_validate({**base, "explore": explore})
        (folder / "config.json").write_text(json.dumps(config.model_dump(mode="json")))
        rows = [{"episode": e, "success_rate": e / 40, "wall_s": e * 1.0} for e in (10, 20)]
        (folder / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    client = TestClient(page_app(FolderView(tmp_path)))
    first = client.get("/figure.json")
    data = first.json()
    arms = {x["name"]: x for x in data["arms"]}
    assert set(arms) == {"counting", "control", "plain"}
    # a runs record written since (a reproduce's FIGURE-runs.json) names the arms anew,
    # though no metrics file changed: the view's version sees it
    record = {"runs": [{"id": "plain", "arm": "no bonus"}]}
    (tmp_path / "mine-runs.json").write_text(json.dumps(record))
    renamed = client.get("/figure.json", headers={"If-None-Match": first.headers["etag"]})
    assert renamed.status_code == 200
    assert {x["name"] for x in renamed.json()["arms"]} == {"counting", "control", "no bonus"}
    (tmp_path / "mine-runs.json").unlink()
    assert arms["counting"]["control"] == "control" and arms["control"]["is_control"]
    assert arms["plain"]["control"] is None and not arms["plain"]["counts"]
    assert arms["counting"]["mean"] == [0.25, 0.5]
    assert data["claims"] == []
    assert [c["arm"] for c in data["controls"]] == ["counting"]
    assert data["progress"]["reached"] == "20 of 40 episodes"


def test_a_folder_with_no_runs_is_refused_with_its_path(tmp_path):
    with pytest.raises(RunsError, match="no runs"):
        FolderView(tmp_path)
    with pytest.raises(RunsError, match="no such folder"):
        folder_view(_args(tmp_path / "missing"))


def test_the_apis_figure_of_an_experiment_is_the_reports(tmp_path):
    """GET /experiments/{id}/figure: a `macb reproduce fig8` experiment's points in the
    store give the report's arms and verdicts; 304 while no point is added; an unknown
    experiment 404; a wrong token 401; an API started without the view 501."""
    body = {**_body(), "episodes": 2000}
    body["name"] = experiment_name(FIG8, body)
    settings = Settings(
        port=0, data_dir=tmp_path / "api", connect=["tcp/127.0.0.1:1"], token="s3cret"
    )
    server = ApiServer(settings, experiment_view).start()
    auth = {"Authorization": "Bearer s3cret"}
    try:
        exp = httpx.post(f"{server.url}/experiments", json=body, headers=auth).json()
        store = Store(server.settings.db_path)
        for run in exp["runs"]:
            store.add_points(run["id"], _rows(run["arm"], run["seed"])[:800])
        url = f"{server.url}/experiments/{exp['id']}/figure"
        got = httpx.get(url, headers=auth)
        assert got.status_code == 200, got.text
        data = got.json()
        assert data["experiment"] == exp["id"] and data["figure"] == "fig8"
        exp = httpx.get(f"{server.url}/experiments/{exp['id']}", headers=auth).json()
        points = {r["id"]: columns(store.points(r["id"])) for r in exp["runs"]}
        a = analyse(FIG8, exp, points)
        for arm in data["arms"]:
            np.testing.assert_array_equal(_nan(arm["mean"]), a.arm(arm["name"]).curve())
        assert [c["verdict"] for c in data["claims"]] == [v for *_, v in claim_verdicts(a)]
        assert [c["verdict"] for c in data["controls"]] == [c[4] for c in control_verdicts(a)]
        etag = got.headers["etag"]
        assert httpx.get(url, headers={**auth, "If-None-Match": etag}).status_code == 304
        store.add_points(exp["runs"][0]["id"], _rows(exp["runs"][0]["arm"], 0)[800:801])
        assert httpx.get(url, headers={**auth, "If-None-Match": etag}).status_code == 200
        store.close()
        assert httpx.get(f"{server.url}/experiments/nope/figure", headers=auth).status_code == 404
        assert httpx.get(url, headers={"Authorization": "Bearer wrong"}).status_code == 401
        page = httpx.get(f"{server.url}/view?experiment={exp['id']}&token=s3cret")
        assert page.status_code == 200 and "function chart(" in page.text
    finally:
        server.stop()
    bare = ApiServer(Settings(port=0, data_dir=tmp_path / "bare", connect=["tcp/127.0.0.1:1"]))
    bare.start()
    try:
        exp = httpx.post(f"{bare.url}/experiments", json={**TINY, "seed": 0}).json()
        assert httpx.get(f"{bare.url}/experiments/{exp['id']}/figure").status_code == 501
    finally:
        bare.stop()


def test_the_apis_figure_is_new_after_a_retry_whose_attempt_has_as_many_points(tmp_path):
    """GET /experiments/{id}/figure with the ETag of a run's earlier attempt: its points
    were deleted by the retry and the new attempt stored as many, ended the same way.
    The data changed, so it is a 200 with the new attempt's points, never a 304."""

    def view(exp: dict, points: dict) -> dict:
        return {r: [p["success_rate"] for p in ps] for r, ps in points.items()}

    settings = Settings(port=0, data_dir=tmp_path / "api", connect=["tcp/127.0.0.1:1"])
    server = ApiServer(settings, view).start()
    store = Store(server.settings.db_path)  # a second connection, as the scheduler has
    assign = Assignment(learner="L", actors=("A",), counter="C", evaluator="E")
    try:
        exp = httpx.post(f"{server.url}/experiments", json={**TINY, "seed": 0}).json()
        run = exp["runs"][0]["id"]
        url = f"{server.url}/experiments/{exp['id']}/figure"

        def attempt(n: int, success: tuple[float, float]) -> str:
            """The run's attempt n: two points, stopped; the figure's ETag then."""
            store.stop_sent(run)  # as the scheduler's pass: a due stop goes out, then the claim
            assert store.claim(run, assign)
            rows = [{"episode": e, "success_rate": s} for e, s in zip((4, 8), success)]
            assert store.add_points(run, rows, attempt=n) == 2
            assert httpx.post(f"{server.url}/runs/{run}/stop").json()["changed"]
            got = httpx.get(url)
            assert got.status_code == 200 and got.json() == {run: list(success)}
            assert httpx.get(url, headers={"If-None-Match": got.headers["etag"]}).status_code == 304
            return got.headers["etag"]

        first = attempt(1, (0.1, 0.2))
        httpx.post(f"{server.url}/experiments/{exp['id']}/retry").raise_for_status()
        queued = httpx.get(url, headers={"If-None-Match": first})
        assert queued.status_code == 200 and queued.json() == {run: []}
        second = attempt(2, (0.9, 0.8))
        assert second != first
        again = httpx.get(url, headers={"If-None-Match": first})
        assert again.status_code == 200 and again.json() == {run: [0.9, 0.8]}
    finally:
        store.close()
        server.stop()


def test_what_was_learned_is_said_in_the_reports_words():
    """`make run`'s last line: the first and last success (mean over seeds), then the
    plateau and convergence as the report defines them; an arm without points says so."""
    from cli.view import learned

    config = {"episodes": 40, "eval_episodes": 10}
    runs = [{"id": f"r{s}", "arm": "a", "seed": s, "config": config} for s in (0, 1)]
    runs.append({"id": "q", "arm": "none yet", "seed": 0, "config": config})
    success = {"r0": [0.0, 0.2, 1.0, 1.0], "r1": [0.2, 0.4, 0.8, 1.0], "q": []}
    points = {
        r: [{"episode": 10 * (i + 1), "success_rate": v} for i, v in enumerate(vs)]
        for r, vs in success.items()
    }
    exp = {"id": "e", "name": "e", "seeds": [0, 1], "runs": runs}
    assert learned(exp, points) == [
        "what was learned (a): success 10% at episode 10 -> 100% at episode 40 (of 10 "
        "noise-free evaluation episodes, mean over seeds); plateau 100%, converged at 30 of "
        "40 episodes",
        "what was learned (none yet): nothing yet, no evaluation point",
    ]
