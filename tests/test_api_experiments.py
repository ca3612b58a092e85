"""POST, GET, stop and retry of /experiments, and an experiment's curves, CSV and plot,
over real HTTP (the API in process on a loopback port, httpx) with a real SQLite file.

No training services: runs stay queued (no free services) and metric points are
written into the store the way the scheduler writes them (tests/conftest.py's `api`
and `client`). Whole runs on real services: tests/test_api_e2e.py."""

from __future__ import annotations

import csv
import io
import json
import math
import statistics
from typing import Literal, get_args, get_origin

import httpx
import pytest
from PIL import Image
from pydantic import ValidationError

from services.api.naming import format_value
from services.api.store import CSV_FIELDS, Store
from shared.config import TrainConfig
from shared.net.messages import Assignment
from tests.harness import TINY, macb, post, row, start_api, wait_for


def test_experiment_expands_into_one_queued_run_per_seed_and_grid_point(client):
    r = post(client, {**TINY, "seeds": [0, 1], "grid": {"beta": [0.2, 0.8], "k": [64, 512]}})
    assert r.status_code == 201, r.text
    exp = r.json()
    assert exp["status"] == "queued" and exp["counts"] == {"queued": 8}
    assert exp["seeds"] == [0, 1] and exp["grid"] == {"beta": [0.2, 0.8], "k": [64, 512]}
    combos = {(r["config"]["beta"], r["config"]["k"], r["config"]["seed"]) for r in exp["runs"]}
    assert combos == {(b, k, s) for b in (0.2, 0.8) for k in (64, 512) for s in (0, 1)}
    for run in exp["runs"]:
        assert run["point"] == {"beta": run["config"]["beta"], "k": run["config"]["k"]}
        assert run["arm"] == f"beta={run['config']['beta']},k={run['config']['k']}"
        assert run["config"]["episodes"] == 12 and run["config"]["hidden"] == [32, 32]
        assert run["progress"] == {
            "episode": 0,
            "episodes": 12,
            "fraction": 0.0,
            "trained_episodes": 0,
        }
    # The run waits in the queue and says what for.
    run_id = exp["runs"][0]["id"]
    waiting = wait_for(
        lambda: client.get(f"/runs/{run_id}").json()["reason"], timeout=10, what="queue reason"
    )
    assert waiting.startswith("waiting: no free") and "learner" in waiting
    assert client.get(f"/runs/{run_id}").json()["status"] == "queued"
    listed = client.get("/experiments").json()
    assert listed["total"] == 1 and listed["experiments"][0]["id"] == exp["id"]
    assert client.get(f"/experiments/{exp['id']}").json()["runs"][3]["id"] == exp["runs"][3]["id"]


def test_seed_defaults_to_the_config_seed_and_name_is_kept(client):
    exp = post(client, {**TINY, "seed": 7, "name": "table 2, small"}).json()
    assert [r["seed"] for r in exp["runs"]] == [7]
    assert exp["name"] == "table 2, small" and exp["seeds"] == [7]
    assert "seed" not in exp["config"] and exp["config"]["k"] == 64


@pytest.fixture
def busless(tmp_path):
    """The API on no bus, and a client of it: its scheduler makes no pass, so only the
    test changes a run. (On a bus each pass, once a second or when the HTTP side wakes
    it, says what every queued run waits for, replacing a retried run's reason.)"""
    server = start_api(tmp_path, None)
    with httpx.Client(base_url=server.url, timeout=20) as c:
        yield server, c
    server.stop()


def test_retry_queues_failed_and_stopped_runs_again_under_their_ids(busless):
    api, client = busless
    exp = post(client, {**TINY, "seeds": [0, 1, 2, 3]}).json()
    stopped, failed, done, waiting = (r["id"] for r in exp["runs"])
    store = Store(api.settings.db_path)  # a second connection, as the scheduler has
    try:
        for run in (stopped, failed, done):
            store.add_points(run, [row(4), row(8)])
        client.post(f"/runs/{stopped}/stop")
        store.finish(failed, "failed", "learner learner died")
        store.finish(done, "completed")
    finally:
        store.close()
    r = client.post(f"/experiments/{exp['id']}/retry")
    assert r.status_code == 200
    out = r.json()
    assert out["changed"] is True and out["retried"] == [stopped, failed]
    assert out["detail"] == "queued 2 run(s) again"
    runs = {x["id"]: x for x in out["experiment"]["runs"]}
    assert [x["id"] for x in out["experiment"]["runs"]] == [r["id"] for r in exp["runs"]]
    assert runs[stopped]["reason"] == "retried (attempt 2; was stopped: stopped by user)"
    assert runs[failed]["reason"] == "retried (attempt 2; was failed: learner learner died)"
    for run in (stopped, failed):
        assert runs[run]["status"] == "queued" and runs[run]["attempts"] == 2
        assert runs[run]["points"] == 0 and runs[run]["started"] is None
        assert client.get(f"/runs/{run}/metrics").json()["points"] == [], "points deleted"
    assert runs[done]["status"] == "completed" and runs[done]["attempts"] == 1
    assert [p["episode"] for p in client.get(f"/runs/{done}/metrics").json()["points"]] == [4, 8]
    assert runs[waiting]["status"] == "queued" and runs[waiting]["attempts"] == 1

    again = client.post(f"/experiments/{exp['id']}/retry").json()  # idempotent
    assert again["changed"] is False and again["retried"] == []
    assert (
        again["detail"] == "nothing to retry: no run is failed or stopped (3 queued, 1 completed)"
    )
    assert {x["id"]: x["attempts"] for x in again["experiment"]["runs"]} == {
        stopped: 2,
        failed: 2,
        done: 1,
        waiting: 1,
    }

    # Only the runs named; a run of another experiment, or none, is an unknown id.
    client.post(f"/experiments/{exp['id']}/stop")
    some = client.post(f"/experiments/{exp['id']}/retry", params={"run": [failed, done]}).json()
    assert some["retried"] == [failed], "a completed run is not retried"
    statuses = {x["id"]: x["status"] for x in some["experiment"]["runs"]}
    assert statuses == {stopped: "stopped", failed: "queued", done: "completed", waiting: "stopped"}
    unknown = client.post(f"/experiments/{exp['id']}/retry", params={"run": ["x-9"]})
    assert unknown.status_code == 404 and "x-9" in unknown.json()["detail"]
    missing = client.post("/experiments/no-such-experiment/retry")
    assert missing.status_code == 404
    assert "no experiment with id 'no-such-experiment'" in missing.json()["detail"]


def test_a_cursor_from_before_a_retry_reads_every_point_of_the_new_attempt(busless):
    """A client polling with `since=next_since` (or resuming events after its
    Last-Event-ID) across a retry: the new attempt's points are numbered on after the
    old attempt's last seq, so the old cursor misses none of them and meets no seq
    twice; the run holds and counts the new attempt's points only."""
    api, client = busless
    exp = post(client, {**TINY, "seeds": [0]}).json()
    run = exp["runs"][0]["id"]
    assign = Assignment(learner="L", actors=("A",), counter="C", evaluator="E")
    store = Store(api.settings.db_path)  # a second connection, as the scheduler has
    try:
        assert store.claim(run, assign)
        assert store.add_points(run, [row(e) for e in (4, 8, 12)], attempt=1) == 3
        page = client.get(f"/runs/{run}/metrics").json()
        cursor = page["next_since"]
        assert (cursor, page["attempt"]) == (3, 1)
        store.finish(run, "failed", "learner died")
        assert client.post(f"/experiments/{exp['id']}/retry").json()["retried"] == [run]
        waiting = client.get(f"/runs/{run}/metrics", params={"since": cursor}).json()
        assert waiting["points"] == [] and waiting["next_since"] == cursor
        assert waiting["attempt"] == 2, "the attempt is the run's, with or without points"
        assert store.claim(run, assign)
        assert store.add_points(run, [row(4, success_rate=0.9), row(8)], attempt=2) == 2
        page = client.get(f"/runs/{run}/metrics", params={"since": cursor}).json()
        assert [(p["seq"], p["episode"]) for p in page["points"]] == [(4, 4), (5, 8)]
        assert page["points"][0]["success_rate"] == 0.9 and page["attempt"] == 2
        assert store.add_points(run, [row(12), row(16)], attempt=2) == 2
        later = client.get(f"/runs/{run}/metrics", params={"since": page["next_since"]}).json()
        assert [(p["seq"], p["episode"]) for p in later["points"]] == [(6, 12), (7, 16)]
        whole = client.get(f"/runs/{run}/metrics").json()["points"]
        assert [p["episode"] for p in whole] == [4, 8, 12, 16], "the new attempt's only"
        got = client.get(f"/runs/{run}").json()
        assert (got["points"], got["attempts"], got["progress"]["episode"]) == (4, 2, 16)
    finally:
        store.close()
    client.post(f"/runs/{run}/stop")  # ended: the event stream ends
    r = client.get(f"/runs/{run}/events", headers={"Last-Event-ID": str(cursor)})
    ids = [x for x in r.text.splitlines() if x.startswith("id:")]
    assert ids == ["id: 4", "id: 5", "id: 6", "id: 7"], r.text


def test_profile_thesis_fills_in_each_runs_options_through_the_api(client):
    """A key the body leaves out is the profile's to fill in, per run: `hash_round` 2 is
    the thesis code's for Cen-MACB only, so it follows each arm's bonus."""
    arms = [{"name": "cen", "explore": "cen-macb"}, {"name": "dis", "explore": "dis-macb"}]
    body = {**TINY, "profile": "thesis", "arms": arms, "landmark_size": 0.05}
    exp = post(client, body).json()
    cen, dis = (r["config"] for r in exp["runs"])
    for config in (cen, dis):
        assert config["profile"] == "thesis" and config["success_terminal"] is True
        assert config["integrator"] == "velocity-first" and config["minibatch"] == "per-agent"
        assert config["landmark_size"] == 0.05, "a key given wins over the profile"
    assert (cen["hash_round"], dis["hash_round"]) == (2, None)
    assert exp["config"]["success_terminal"] is True, "the base shows the profile's options"
    plain = post(client, TINY).json()["runs"][0]["config"]
    assert plain["profile"] == "mpe2" and plain["success_terminal"] is False
    assert plain == TrainConfig(**{**TINY, "seed": 0}).model_dump(mode="json")


# ---------------------------------------------------------------- arms and grids
FIG8_ARMS = [  # thesis figure 8's arms over a Cen-MADDPG base
    {"name": "no bonus", "explore": "none"},
    {"name": "dis-macb", "explore": "dis-macb"},
    {"name": "cen-macb", "explore": "cen-macb"},
    {"name": "control", "explore": "constant"},
]


def _grid_values(name: str) -> list:
    """Two or more values of a config key for a grid: every choice of a Literal, both
    booleans, or TINY's value and another valid one."""
    field = TrainConfig.model_fields[name]
    choices = [v for v in get_args(field.annotation) if isinstance(v, str)]
    if get_origin(field.annotation) is Literal:
        return choices
    if field.annotation is bool:
        return [False, True]
    value = TINY.get(name, field.default)
    other = {
        "learner_lanes": 2,
        "hidden": [16],
        "beta": 0.25,
        "gamma": 0.95,
        "tau": 0.01,
        "lr_actor": 1e-4,
        "lr_critic": 1e-4,
        "noise_sigma": 0.2,
        "agents": 3,
        "episode_len": 25,
        "learning_starts": 0,
        "landmark_size": 0.075,  # optional: None (the task's) and a size
        "hash_round": 2,
        "task": "spread",
        "task_kwargs": {"max_cycles": 25},  # over a custom task's base (CUSTOM_BASE)
        "success_key": "at_goal",
        "device": "cuda",  # a name the config takes; the learner checks it is there
        # optional: None (the exact table) and a sketch, written whole as a run stores it
        "count_sketch": {"width": 1024, "depth": 4, "memory_mb": None, "conservative": True},
        # optional: None (beta constant; no early stop) and a rule, written whole
        "beta_schedule": {"kind": "linear", "end": 0.0, "horizon": 1000, "unit": "episodes"},
        "early_stop": {
            "rule": "success_at_least",
            "threshold": 0.9,
            "patience": 3,
            "smooth": 1,
            "min_delta": 0.0,
        },
    }.get(name, value + 1 if isinstance(value, int) else value)
    return [value, other]


# The keys only a custom task takes are swept over one (docs/tasks.md's example).
CUSTOM_BASE = {"task": "examples.reference:parallel_env"}


def test_a_grid_may_sweep_every_config_key_but_the_seed(client):
    """Every key is accepted with every value its field takes; a combination that breaks
    a cross-field rule (task simple with Cen-MADDPG) is refused, naming the point."""
    for name in TrainConfig.model_fields:
        if name == "seed":
            continue
        values = _grid_values(name)
        base = {**TINY, **CUSTOM_BASE} if name in ("task_kwargs", "success_key") else TINY
        r = post(client, {**base, "grid": {name: values}})
        invalid = []
        for v in values:
            try:
                TrainConfig.model_validate({**base, name: v})
            except ValidationError:
                invalid.append(v)
        if invalid:
            assert r.status_code == 422, (name, r.text)
            (err,) = r.json()["detail"]
            assert err["field"] == "grid"
            assert err["msg"].startswith(f"grid: point {name}={format_value(invalid[0])}: config: ")
            values = [v for v in values if v not in invalid]
            assert len(values) >= 2, name
            r = post(client, {**base, "grid": {name: values}})
        assert r.status_code == 201, (name, r.text)
        runs = r.json()["runs"]
        assert [run["config"][name] for run in runs] == values, name
        assert [run["point"] for run in runs] == [{name: v} for v in values]
        assert [run["arm"] for run in runs] == [f"{name}={format_value(v)}" for v in values]
        assert r.json()["grid"] == {name: values}


def test_arms_are_crossed_with_seeds_and_the_grid_and_each_run_carries_its_arm(client):
    r = post(client, {**TINY, "seeds": [0, 1], "arms": FIG8_ARMS})
    assert r.status_code == 201, r.text
    exp = r.json()
    assert exp["arms"] == FIG8_ARMS and exp["grid"] is None and exp["seeds"] == [0, 1]
    assert [(x["arm"], x["seed"]) for x in exp["runs"]] == [
        (a["name"], s) for a in FIG8_ARMS for s in (0, 1)
    ], "arms outer, seeds inner, in the order given"
    for run in exp["runs"]:
        arm = next(a for a in FIG8_ARMS if a["name"] == run["arm"])
        assert run["point"] == {"explore": arm["explore"]}
        assert run["config"]["explore"] == arm["explore"]
        assert run["config"]["k"] == 64 and run["config"]["algo"] == "cen-maddpg"
    assert exp["name"] == "speaker_listener: no bonus | dis-macb | cen-macb | control"

    # Arms x grid x seeds: the arm's keys and the grid point's both; the names both.
    arms = [{"name": "cen", "explore": "cen-macb"}, {"name": "ctl", "explore": "constant"}]
    body = {**TINY, "arms": arms, "grid": {"beta": [0.2, 0.8]}, "seeds": [5, 6]}
    exp = post(client, body).json()
    assert len(exp["runs"]) == 8
    assert [x["arm"] for x in exp["runs"][::2]] == [
        "cen beta=0.2",
        "cen beta=0.8",
        "ctl beta=0.2",
        "ctl beta=0.8",
    ]
    first = exp["runs"][0]
    assert first["point"] == {"explore": "cen-macb", "beta": 0.2} and first["seed"] == 5
    assert (first["config"]["explore"], first["config"]["beta"]) == ("cen-macb", 0.2)

    # A grid over several keys: points named key=value in config-field order.
    body = {**TINY, "grid": {"beta": [0.2], "explore": ["none", "dis-macb"], "k": [32]}}
    exp = post(client, body).json()
    assert [x["arm"] for x in exp["runs"]] == [
        "explore=none,beta=0.2,k=32",
        "explore=dis-macb,beta=0.2,k=32",
    ]

    # The base alone may break a cross-field rule that every arm fixes.
    body = {"task": "simple", "episodes": 8, "arms": [{"name": "ddpg", "algo": "ddpg"}]}
    exp = post(client, body).json()
    assert exp["config"]["algo"] == "cen-maddpg", "the base as given"
    assert exp["runs"][0]["config"]["algo"] == "ddpg" and exp["runs"][0]["arm"] == "ddpg"
    # Without arms or grid the one arm is named after its algo and bonus.
    assert post(client, TINY).json()["runs"][0]["arm"] == "cen-maddpg + cen-macb"


def test_refusals_of_grids_and_arms_say_what_and_where(client):
    def detail(body):
        r = post(client, body)
        assert r.status_code == 422, r.text
        (err,) = r.json()["detail"]
        return err["field"], err["msg"]

    field, msg = detail({**TINY, "grid": {"seed": [1, 2]}})
    assert field == "grid.seed" and "list them in `seeds`" in msg
    field, msg = detail({**TINY, "arms": [{"name": "a"}, {"name": "b", "seeds": [1]}]})
    assert field == "arms.1.seeds" and "not a grid or arm key" in msg
    field, msg = detail({**TINY, "grid": {"task": ["spread", "simple"], "agents": [2, 3]}})
    assert field == "grid"
    assert msg == (
        "grid: point task=simple,agents=2: config: algo cen-maddpg needs several agents; "
        "task simple has one: use ddpg (1 more combination(s) are invalid too)"
    )
    field, msg = detail({**TINY, "arms": [{"name": "ok"}, {"name": "one", "algo": "ddpg"}]})
    assert field == "arms.1"
    assert msg.startswith("arms.1: arm 'one': config: algo ddpg trains one agent")
    body = {**TINY, "arms": [{"name": "one", "algo": "ddpg"}], "grid": {"beta": [0.1]}}
    assert detail(body)[1].startswith("arms.0: arm 'one' with grid point beta=0.1: config: ")
    field, msg = detail({**TINY, "grid": {"gama": [0.9]}})
    assert field == "grid.gama" and "unknown key" in msg
    assert client.get("/experiments").json()["total"] == 0, "nothing was stored"


def _store_points(store: Store, exp: dict, values: dict[tuple[str, int], list]) -> None:
    """(arm, seed) -> [(episode, success_rate), ...] into the runs of `exp`."""
    for run in exp["runs"]:
        rows = [row(e, success_rate=v) for e, v in values.get((run["arm"], run["seed"]), [])]
        store.add_points(run["id"], rows)


ARM_POINTS = {  # two arms x three seeds; seed 2 of arm b has no point at episode 8
    ("a", 0): [(4, 0.0), (8, 0.2)],
    ("a", 1): [(4, 0.3), (8, 0.4)],
    ("a", 2): [(4, 0.6), (8, 0.9)],
    ("b", 0): [(4, 1.0), (8, 1.0)],
    ("b", 1): [(4, 0.5), (8, 0.0)],
    ("b", 2): [(4, 0.0)],
}


def _arms_experiment(api, client) -> dict:
    arms = [{"name": "a", "explore": "cen-macb"}, {"name": "b", "explore": "constant"}]
    exp = post(client, {**TINY, "seeds": [0, 1, 2], "arms": arms}).json()
    store = Store(api.settings.db_path)
    try:
        _store_points(store, exp, ARM_POINTS)
    finally:
        store.close()
    return exp


def test_curves_give_one_series_per_arm_with_mean_and_std_over_its_seeds(api, client):
    exp = _arms_experiment(api, client)
    data = client.get(
        f"/experiments/{exp['id']}/curves", params={"metric": ["success_rate", "episode"]}
    ).json()
    a, b = data["metrics"]["success_rate"]
    assert (a["name"], b["name"]) == ("a", "b") and (a["label"], b["label"]) == ("a", "b")
    assert a["seeds"] == [0, 1, 2] and b["seeds"] == [0, 1, 2]
    assert a["runs"] == [r["id"] for r in exp["runs"] if r["arm"] == "a"]
    assert a["point"] == {"explore": "cen-macb"} and b["point"] == {"explore": "constant"}
    for curve, arm in ((a, "a"), (b, "b")):
        assert curve["episode"] == [4, 8]
        for i, episode in enumerate((4, 8)):
            vs = [v for s in range(3) for e, v in ARM_POINTS[(arm, s)] if e == episode]
            assert curve["n"][i] == len(vs)
            assert curve["mean"][i] == pytest.approx(statistics.fmean(vs))
            assert curve["std"][i] == pytest.approx(statistics.pstdev(vs))
            assert curve["lo"][i] == pytest.approx(curve["mean"][i] - curve["std"][i])
            assert curve["hi"][i] == pytest.approx(curve["mean"][i] + curve["std"][i])
    assert b["n"] == [3, 2] and b["mean"] == pytest.approx([0.5, 0.5])
    assert b["std"] == pytest.approx([math.sqrt(1 / 6), 0.5])
    # Another metric groups the same way.
    assert [c["name"] for c in data["metrics"]["episode"]] == ["a", "b"]
    assert data["metrics"]["episode"][0]["mean"] == pytest.approx([4.0, 8.0])


def test_experiment_csv_holds_every_point_of_every_run_arm_seed_and_run_first(api, client):
    exp = _arms_experiment(api, client)
    r = client.get(f"/experiments/{exp['id']}/metrics.csv")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
    assert f"{exp['id']}-metrics.csv" in r.headers["content-disposition"]
    header = r.text.splitlines()[0].split(",")
    assert header == ["arm", "seed", "run", *CSV_FIELDS]
    table = list(csv.DictReader(io.StringIO(r.text)))
    assert len(table) == sum(len(v) for v in ARM_POINTS.values())
    by_run = {x["id"]: x for x in exp["runs"]}
    got = {}
    for line in table:
        run = by_run[line["run"]]
        assert (line["arm"], int(line["seed"])) == (run["arm"], run["seed"])
        got.setdefault((line["arm"], int(line["seed"])), []).append(
            (int(line["episode"]), float(line["success_rate"]))
        )
    assert got == ARM_POINTS
    assert [line["run"] for line in table] == sorted(
        (line["run"] for line in table), key=lambda x: int(x.rsplit("-", 1)[1])
    ), "runs in their order"
    # A column only some points have comes after the standard ones, blank elsewhere.
    store = Store(api.settings.db_path)
    store.add_points(exp["runs"][0]["id"], [row(12, probe_extra=0.5)])
    store.close()
    text = client.get(f"/experiments/{exp['id']}/metrics.csv").text
    assert text.splitlines()[0].endswith(f",{CSV_FIELDS[-1]},probe_extra")
    lines = list(csv.DictReader(io.StringIO(text)))
    assert [x["probe_extra"] for x in lines if x["probe_extra"]] == ["0.5"]


def test_plot_overlays_every_arm_with_its_name_in_the_legend(api, client, tmp_path):
    from services.api.plot import draw_curves, figure_legend, plot_curves

    exp = _arms_experiment(api, client)
    data = client.get(f"/experiments/{exp['id']}/curves", params={"metric": "success_rate"}).json()
    fig = draw_curves(data, "success_rate")
    assert figure_legend(fig) == ["a (3 seeds)", "b (3 seeds)"]
    (ax,) = fig.axes
    lines = ax.get_lines()
    assert [list(line.get_ydata()) for line in lines] == [
        c["mean"] for c in data["metrics"]["success_rate"]
    ]
    assert len(ax.collections) == 2, "one band per arm"
    assert lines[0].get_color() != lines[1].get_color()
    out = plot_curves(data, "success_rate", tmp_path / "fig" / "arms.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with Image.open(out) as png:
        assert json.loads(png.text["Legend"]) == ["a (3 seeds)", "b (3 seeds)"]

    # The command, from the API and from the store file; `macb ls` shows the arms.
    for source in (("--api", api.url), ("--db", str(api.settings.db_path))):
        png_path = tmp_path / f"cli{source[0]}.png"
        done = macb("plot", exp["id"], "-o", str(png_path), *source)
        assert done.returncode == 0, done.stderr
        with Image.open(png_path) as png:
            assert json.loads(png.text["Legend"]) == ["a (3 seeds)", "b (3 seeds)"]
    db = str(api.settings.db_path)
    svg = macb("plot", exp["id"], "-o", str(tmp_path / "arms.svg"), "--db", db)
    assert svg.returncode == 0, svg.stderr  # another format: no legend chunk to write
    assert (tmp_path / "arms.svg").read_text().lstrip().startswith("<?xml")
    odd = macb("plot", exp["id"], "-o", str(tmp_path / "arms.xyz"), "--db", db)
    assert odd.returncode == 2 and "arms.xyz" in odd.stderr and "Traceback" not in odd.stderr
    assert "matplotlib writes no .xyz" in odd.stderr
    bare = macb("plot", exp["id"], "-o", str(tmp_path / "new" / "arms"), "--db", db)
    assert bare.returncode == 0 and f"wrote {tmp_path / 'new' / 'arms.png'}" in bare.stdout
    with Image.open(tmp_path / "new" / "arms.png") as png:  # no suffix: a PNG, its legend
        assert json.loads(png.text["Legend"]) == ["a (3 seeds)", "b (3 seeds)"]
    typo = tmp_path / "typo" / "api.sqlite3"
    missing = macb("plot", exp["id"], "-o", str(tmp_path / "x.png"), "--db", str(typo))
    assert missing.returncode == 2 and f"no store file {typo}" in missing.stderr
    assert not typo.parent.exists()  # not made, nor its folder
    listed = macb("ls", "--api", api.url)
    assert listed.returncode == 0, listed.stderr
    for run in exp["runs"]:
        (line,) = [x for x in listed.stdout.splitlines() if run["id"] in x]
        assert f"arm={run['arm']} " in line and f"seed={run['seed']}" in line


# ---------------------------------------------------------------- bad input
BAD_BODIES = [
    # (what, request kwargs, status, field named in the answer)
    ("malformed JSON", {"content": b'{"task": "spread",', "json_ct": True}, 400, "body"),
    ("not an object", {"json": [1, 2]}, 422, "body"),
    ("wrong type", {"json": {**TINY, "episodes": "many"}}, 422, "episodes"),
    ("wrong type in a list", {"json": {**TINY, "hidden": [32, "x"]}}, 422, "hidden.1"),
    ("bool for a list", {"json": {**TINY, "seeds": True}}, 422, "seeds"),
    ("out of range", {"json": {**TINY, "beta": 101}}, 422, "beta"),
    ("out of range k", {"json": {**TINY, "k": 0}}, 422, "k"),
    ("negative seed", {"json": {**TINY, "seeds": [-1]}}, 422, "seeds.0"),
    ("grid out of range", {"json": {**TINY, "grid": {"k": [64, 99999]}}}, 422, "grid.k.1"),
    ("NaN", {"content": b'{"beta": NaN}', "json_ct": True}, 422, "beta"),
    ("unknown field", {"json": {**TINY, "betta": 0.3}}, 422, "betta"),
    ("unknown grid key", {"json": {**TINY, "grid": {"betta": [0.9]}}}, 422, "grid.betta"),
    ("bad combination", {"json": {"task": "simple", "algo": "cen-maddpg"}}, 422, "config"),
    ("seed as a grid key", {"json": {**TINY, "grid": {"seed": [1, 2]}}}, 422, "grid.seed"),
    ("seeds as a grid key", {"json": {**TINY, "grid": {"seeds": [1]}}}, 422, "grid.seeds"),
    (
        "grid value of a wrong kind",
        {"json": {**TINY, "grid": {"explore": ["x"]}}},
        422,
        "grid.explore.0",
    ),
    ("repeated grid value", {"json": {**TINY, "grid": {"beta": [0.2, 0.2]}}}, 422, "grid.beta"),
    ("empty grid list", {"json": {**TINY, "grid": {"reward": []}}}, 422, "grid.reward"),
    (
        "invalid grid combination",
        {"json": {**TINY, "grid": {"algo": ["cen-maddpg", "ddpg"]}}},
        422,
        "grid",
    ),
    ("seed in an arm", {"json": {**TINY, "arms": [{"name": "a", "seed": 3}]}}, 422, "arms.0.seed"),
    (
        "unknown arm key",
        {"json": {**TINY, "arms": [{"name": "a", "betta": 1}]}},
        422,
        "arms.0.betta",
    ),
    ("arm without a name", {"json": {**TINY, "arms": [{"explore": "none"}]}}, 422, "arms.0.name"),
    (
        "arm value out of range",
        {"json": {**TINY, "arms": [{"name": "a", "k": 0}]}},
        422,
        "arms.0.k",
    ),
    (
        "repeated arm name",
        {"json": {**TINY, "arms": [{"name": "a"}, {"name": "a", "beta": 0.1}]}},
        422,
        "arms.1.name",
    ),
    (
        "an arm sets a key the grid sweeps",
        {"json": {**TINY, "arms": [{"name": "a", "beta": 0.1}], "grid": {"beta": [0.2, 0.8]}}},
        422,
        "arms.0.beta",
    ),
    (
        "invalid arm combination",
        {"json": {**TINY, "arms": [{"name": "ok"}, {"name": "dd", "algo": "ddpg"}]}},
        422,
        "arms.1",
    ),
    ("no arms", {"json": {**TINY, "arms": []}}, 422, "arms"),
    (
        "too many runs with arms",
        {
            "json": {
                **TINY,
                "arms": [{"name": str(i)} for i in range(4)],
                "grid": {"k": list(range(1, 9))},
                "seeds": list(range(9)),
            }
        },
        422,
        "arms x grid x seeds",
    ),
    (
        "a huge product of grid lists",
        {"json": {**TINY, "grid": {k: list(range(1, 33)) for k in ("k", "episodes", "threads")}}},
        422,
        "seeds x grid",
    ),
    ("seed and seeds", {"json": {**TINY, "seed": 1, "seeds": [1]}}, 422, "seed"),
    ("repeated seed", {"json": {**TINY, "seeds": [1, 1]}}, 422, "seeds"),
    (
        "too many runs",
        {"json": {**TINY, "seeds": list(range(64)), "grid": {"k": [1, 2, 3, 4, 5]}}},
        422,
        "seeds x grid",
    ),
    ("huge body", {"json": {**TINY, "name": "x" * 70_000}}, 413, None),
    (
        "huge chunked body",
        {"content": iter([b"{" + b" " * 40_000] * 3), "json_ct": True},
        413,
        None,
    ),
    ("not JSON content type", {"content": json.dumps(TINY), "ct": "text/plain"}, 415, None),
    ("form body", {"data": {"task": "spread"}}, 415, None),
]


def test_bad_input_gets_the_right_status_names_the_field_and_changes_nothing(api, client):
    exp = post(client, {**TINY, "seeds": [0]}).json()
    run = exp["runs"][0]["id"]
    # The scheduler notes what the run waits for; from then on nothing should change.
    wait_for(lambda: client.get(f"/runs/{run}").json()["reason"], timeout=10, what="queued")
    store = Store(api.settings.db_path)
    before = store.snapshot()
    for what, kw, status, field in BAD_BODIES:
        kw = dict(kw)
        headers = {}
        if kw.pop("json_ct", False):
            headers["content-type"] = "application/json"
        if "ct" in kw:
            headers["content-type"] = kw.pop("ct")
        r = client.post("/experiments", headers=headers, **kw)
        assert r.status_code == status, (what, r.status_code, r.text)
        detail = r.json()["detail"]
        if field is not None:
            assert field in [e["field"] for e in detail], (what, detail)
            assert all(e["msg"] for e in detail)
    for method, path in [
        ("GET", "/experiments/nope"),
        ("POST", "/experiments/nope/stop"),
        ("GET", "/experiments/nope/curves"),
        ("GET", "/experiments/nope/metrics.csv"),
        ("GET", "/runs/nope"),
        ("POST", "/runs/nope/stop"),
        ("GET", "/runs/nope/metrics"),
        ("GET", "/runs/nope/metrics.csv"),
        ("GET", "/runs/nope/events"),
    ]:
        r = client.request(method, path)
        assert r.status_code == 404, (method, path, r.text)
        assert "nope" in r.json()["detail"]
    for path, params in [
        (f"/runs/{run}/metrics", {"since": -1}),
        (f"/runs/{run}/metrics", {"limit": 0}),
        (f"/runs/{run}/metrics", {"since": "x"}),
        ("/experiments", {"limit": 100_000}),
        (f"/experiments/{exp['id']}/curves", {"metric": "a b"}),
        (f"/experiments/{exp['id']}/curves", {"metric": "nosuch"}),
    ]:
        assert client.get(path, params=params).status_code == 422, (path, params)
    # An unknown metric gave empty curves (200): refused naming it and what may be asked.
    r = client.get(f"/experiments/{exp['id']}/curves", params={"metric": "nosuch"})
    assert "unknown metric 'nosuch'" in r.text and "success_rate" in r.text, r.text
    assert client.delete(f"/runs/{run}").status_code == 405
    assert store.snapshot() == before, "a refused request changed stored state"
    store.close()


def test_an_arm_may_count_in_a_sketch_and_an_invalid_one_is_refused_naming_it(client):
    """`count_sketch` is a map: an arm sets it whole, each run stores it whole."""
    sketch = {"width": None, "depth": 2, "memory_mb": 1.0, "conservative": False}
    arms = [{"name": "exact"}, {"name": "sketch", "count_sketch": sketch}]
    r = post(client, {**TINY, "arms": arms})
    assert r.status_code == 201, r.text
    assert [run["config"]["count_sketch"] for run in r.json()["runs"]] == [None, sketch]
    bad = [{"name": "bad", "count_sketch": {"width": 64, "memory_mb": 1}}]
    r = post(client, {**TINY, "arms": bad})
    assert r.status_code == 422, r.text
    (err,) = r.json()["detail"]
    assert err["field"] == "arms.0.count_sketch" and err["msg"].startswith(
        "give width or memory_mb"
    )


@pytest.mark.parametrize(
    ("task", "why"),
    [
        # os, reached through a module an allowed one imported
        ("mpe2._mpe_utils.simple_env:os.system", "'os' is a module (os)"),
        ("mpe2._mpe_utils.simple_env:__builtins__.get", "'__builtins__' is private"),
        # a callable the allowed module imported from elsewhere (typing)
        ("mpe2._mpe_utils.simple_env:Any", "Any is defined in typing, not in a package"),
    ],
)
def test_a_task_reaching_outside_the_allowed_packages_is_refused_uncalled(
    tmp_path, router, task, why
):
    """MACB_API_TASK_MODULES bounds what a body may make the API call: not only the
    module a task names but the factory it reaches, which must be defined in those
    packages (or be PettingZoo's env wrapper, as every mpe2 `parallel_env` is)."""
    server = start_api(tmp_path, router, task_modules=["mpe2"])
    try:
        marker = tmp_path / "called"
        body = {**TINY, "task": task, "task_kwargs": {"command": f"touch {marker}"}}
        got = httpx.post(f"{server.url}/experiments", json=body, timeout=30)
        assert got.status_code == 422, got.text
        (err,) = got.json()["detail"]
        assert err["field"] == "task" and why in err["msg"], err
        assert not marker.exists(), "the factory was called"
        assert httpx.get(f"{server.url}/experiments", timeout=30).json()["experiments"] == []
        # mpe2's own factory is PettingZoo's wrapper: still taken with only mpe2 allowed
        ok = {**TINY, "task": "mpe2.simple_speaker_listener_v4:parallel_env", "episodes": 4}
        ok["task_kwargs"] = {"continuous_actions": True}
        assert httpx.post(f"{server.url}/experiments", json=ok, timeout=30).status_code == 201
    finally:
        server.stop()


def test_a_body_the_store_could_store_but_not_show_is_refused_and_stores_nothing(busless):
    """A lone surrogate in a custom task's kwargs is valid JSON text but not UTF-8: once
    stored, every listing showing it would fail to encode. Refused with 422 naming the
    field, nothing stored, every listing still answering."""
    _, client = busless
    raw = (
        b'{"task": "mpe2.simple_speaker_listener_v4:parallel_env", "algo": "cen-maddpg",'
        b' "episodes": 4, "task_kwargs": {"render_mode": "\\ud800", "continuous_actions": true}}'
    )
    got = client.post("/experiments", content=raw, headers={"content-type": "application/json"})
    assert got.status_code == 422, got.text
    (err,) = got.json()["detail"]
    assert err["field"] == "task_kwargs" and "not valid UTF-8" in err["msg"], err
    listing = client.get("/experiments")
    assert listing.status_code == 200 and listing.json()["experiments"] == []
