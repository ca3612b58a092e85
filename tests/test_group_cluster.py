"""Run groups through the API: the scheduler starts an experiment's runs that can share
a group (`MACB_API_GROUP_SIZE`) on one learner, actor and evaluator, and each run is the
one-process group's run, bit for bit. Real processes: router, counter, learner,
evaluator, one actor and the API, over loopback."""

from __future__ import annotations

import httpx

from cli.trainer import train_group
from shared.config import make_config
from tests.harness import api_cluster, wait_for
from tests.test_lockstep import BASE, CASES, compare

BODY = {**BASE, **CASES["speaker_listener-cen-macb-thesis"]}


def finished(url: str, exp_id: str) -> dict | bool:
    exp = httpx.get(f"{url}/experiments/{exp_id}").json()
    return exp if exp["status"] not in ("queued", "running") else False


def test_the_api_runs_an_experiments_seeds_as_one_group_bit_for_bit(tmp_path):
    with api_cluster(tmp_path, api_env={"MACB_API_GROUP_SIZE": "3"}) as cluster:
        url = cluster.url
        body = {k: v for k, v in BODY.items() if k != "seed"}
        exp = httpx.post(f"{url}/experiments", json={**body, "seeds": [3, 4, 5]}).json()
        ids = [r["id"] for r in exp["runs"]]
        done = wait_for(lambda: finished(url, exp["id"]), timeout=300, what="the experiment")
        assert done["status"] == "completed", done
        runs = [httpx.get(f"{url}/runs/{i}").json() for i in ids]
        for run in runs:  # one group: the same services, the group's runs in order
            assert run["assign"]["group"] == ids and run["assign"]["actors"] == ["actor0"]
        configs = [make_config(run["config"]) for run in runs]
        local = train_group(configs, [tmp_path / f"l{r}" for r in range(3)], progress=False)
        for r, run_id in enumerate(ids):
            points = httpx.get(f"{url}/runs/{run_id}/metrics").json()["points"]
            rows = [{k: v for k, v in p.items() if k != "seq"} for p in points]
            diffs = compare(rows, local[r])
            assert not diffs, f"run {r}\n" + "\n".join(diffs[:20])

        # Stopping one run of a group stops the group (its runs step together); the
        # services are then free, and the next experiment runs.
        longer = {**body, "episodes": 400}
        exp = httpx.post(f"{url}/experiments", json={**longer, "seeds": [1, 2]}).json()
        ids = [r["id"] for r in exp["runs"]]
        wait_for(
            lambda: all(httpx.get(f"{url}/runs/{i}").json()["status"] == "running" for i in ids),
            timeout=60,
            what="the group running",
        )
        assert httpx.post(f"{url}/runs/{ids[0]}/stop").status_code in (200, 202)
        done = wait_for(lambda: finished(url, exp["id"]), timeout=60, what="the group stopped")
        other = httpx.get(f"{url}/runs/{ids[1]}").json()
        assert other["status"] in ("stopped", "failed"), other
        assert ids[0] in (other["reason"] or ""), other
        exp = httpx.post(f"{url}/experiments", json={**body, "seeds": [7]}).json()
        done = wait_for(lambda: finished(url, exp["id"]), timeout=120, what="the next run")
        assert done["status"] == "completed", done


def test_the_api_groups_runs_with_an_early_stop_rule_and_ends_one_alone(tmp_path):
    """Arms that differ in `early_stop` share a group; the run its rule ends at episode 6
    is stored completed with the rule's reason, its last point marked, while the other
    run of its group goes on to the end: both with `macb train`'s rows."""
    from cli.trainer import train

    rule = {"rule": "success_at_least", "threshold": 0.0, "patience": 2}
    with api_cluster(tmp_path, api_env={"MACB_API_GROUP_SIZE": "3"}) as cluster:
        url = cluster.url
        body = {k: v for k, v in BODY.items() if k != "seed"}
        arms = [{"name": "stops", "early_stop": rule}, {"name": "goes on"}]
        exp = httpx.post(f"{url}/experiments", json={**body, "seeds": [3], "arms": arms}).json()
        ids = [r["id"] for r in exp["runs"]]
        done = wait_for(lambda: finished(url, exp["id"]), timeout=300, what="the experiment")
        assert done["status"] == "completed", done
        runs = [httpx.get(f"{url}/runs/{i}").json() for i in ids]
        assert all(run["assign"]["group"] == ids for run in runs), runs
        assert [run["status"] for run in runs] == ["completed", "completed"]
        for r, run in enumerate(runs):
            points = httpx.get(f"{url}/runs/{run['id']}/metrics").json()["points"]
            rows = [{k: v for k, v in p.items() if k != "seq"} for p in points]
            local = train(make_config(run["config"]), tmp_path / f"l{r}", progress=False)
            diffs = compare(rows, local)
            assert not diffs, f"run {r}\n" + "\n".join(diffs[:20])
            if r == 0:
                assert rows[-1]["episode"] == 6 and run["reason"] == rows[-1]["stop_reason"]
                assert run["reason"].startswith("early_stop success_at_least at episode 6")
            else:
                assert rows[-1]["episode"] == BODY["episodes"] and not run["reason"], run


def test_another_attempts_late_row_neither_stops_a_lockstep_run_nor_is_stored(tmp_path):
    """In lockstep the learner reads each point's row for `early_stop`, and a row whose
    evaluator found the rule holding stops the run there. A row of another attempt of
    the run (an ended attempt's evaluator, late, or a later one's) names its attempt:
    the learner reads none of it and the API stores none, so the run goes to its end
    with `macb train`'s rows."""
    from contextlib import closing

    from cli.trainer import train
    from shared.net import bus as keys
    from shared.net.bus import Bus
    from shared.net.messages import Metrics
    from shared.net.wire import encode

    never = {"rule": "success_at_least", "threshold": 1.0, "patience": 100}
    with api_cluster(tmp_path) as cluster, closing(Bus([cluster.endpoint])) as bus:
        url = cluster.url
        body = {**BODY, "episodes": 30, "early_stop": never}
        exp = httpx.post(f"{url}/experiments", json=body).json()
        run_id = exp["runs"][0]["id"]
        # (episode 28 is no point: no row of this attempt comes for it, whenever it comes)
        stale = {
            "episode": 28,
            "env_steps": 280,
            "success_rate": 1.0,
            "stop_reason": "early_stop (stale)",
        }
        msg = encode(Metrics(run_id, source="eval", attempt=2, data=stale))

        # Sent until the run's first point is stored: its learner has subscribed by then
        # and has 27 episodes to go.
        def sent_till_a_point() -> bool:
            bus.put(keys.k_metrics(run_id, "eval"), msg)
            return httpx.get(f"{url}/runs/{run_id}").json()["points"] >= 1

        wait_for(sent_till_a_point, timeout=60, what="a point stored")
        bus.put(keys.k_metrics(run_id, "eval"), msg)
        done = wait_for(lambda: finished(url, exp["id"]), timeout=300, what="the experiment")
        run = httpx.get(f"{url}/runs/{run_id}").json()
        assert done["status"] == "completed" and run["reason"] is None, run
        assert run["attempts"] == 1, run
        points = httpx.get(f"{url}/runs/{run_id}/metrics").json()["points"]
        rows = [{k: v for k, v in p.items() if k != "seq"} for p in points]
        assert all(r.get("stop_reason") is None for r in rows), rows
        local = train(make_config(run["config"]), tmp_path / "alone", progress=False)
        diffs = compare(rows, local)
        assert not diffs, "\n".join(diffs[:20])
