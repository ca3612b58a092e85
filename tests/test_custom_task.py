"""Your own task (`task: package.module:factory`): the adapter, its refusals, and runs
through `macb train` and through the cluster's API.

Real PettingZoo envs throughout: mpe2's simple_reference (examples/reference.py adds
its success key) and simple, and tests/custom_envs.py's TinyEnv, whose spaces, early
ends and success info the task_kwargs choose and which records what it was sent.
"""

from __future__ import annotations

import json
import subprocess

import httpx
import numpy as np
import pytest

from cli.trainer import train
from shared.config import ConfigError, make_config
from shared.envs.tasks import make_task_for, task_spec_for
from shared.run.rollout import Collector, evaluate
from tests.harness import NETS, api_cluster, macb, wait_for
from tests.test_tensorboard import assert_same, expected, read_back

TINY = "tests.custom_envs:tiny"
REFERENCE = {
    "task": "examples.reference:parallel_env",
    "task_kwargs": {"max_cycles": 10},
    "success_key": "at_goal",
    "episode_len": 10,
}
SMALL = {**NETS, "k": 32}


def refused(**data) -> str:
    with pytest.raises(ConfigError) as err:
        make_config(data)
    return str(err.value)


@pytest.mark.parametrize(
    ("kwargs", "says"),
    [
        (
            {"obs": "discrete"},
            "task: tests.custom_envs:tiny: agent a0: observation space Discrete(4) is not a Box",
        ),
        ({"act": "discrete"}, "agent a0: action space Discrete(5) is not a Box"),
        (
            {"act": "unbounded"},
            "agent a0: action space Box(-inf, inf, (2,), float32) needs finite bounds",
        ),
        (
            {"wrong_obs_shape": True},
            "agent a0: observation of shape (4,) after reset, but its "
            "space is Box(-10.0, 10.0, (3,), float32)",
        ),
    ],
)
def test_spaces_that_cannot_be_trained_are_refused_naming_the_agent_and_the_space(kwargs, says):
    msg = refused(task=TINY, task_kwargs=kwargs, algo="dis-maddpg", explore="dis-macb")
    assert says in msg


@pytest.mark.parametrize(
    ("task", "says"),
    [
        ("tests.custom_envs:NOT_A_FACTORY", "NOT_A_FACTORY is a int, not a factory"),
        ("tests.custom_envs:raises", "the factory raised RuntimeError: this factory always"),
        ("tests.custom_envs:gives_a_dict", "gave a dict, not a PettingZoo ParallelEnv"),
        ("tests.custom_envs:nothing", "tests.custom_envs has no attribute 'nothing'"),
        ("tests.no_such_module:tiny", "cannot import tests.no_such_module"),
        ("mpe2.simple_v3:env", "gave an AEC env"),
        ("tests.custom_envs:tiny extra", "a custom task is `package.module:factory`"),
    ],
)
def test_bad_factories_are_refused_naming_the_task(task, says):
    msg = refused(task=task, algo="dis-maddpg")
    assert msg.startswith("task: ") and says in msg


def test_config_rules_of_custom_tasks():
    # mpe2 builds discrete actions unless asked: the hint says how.
    msg = refused(task="mpe2.simple_reference_v3:parallel_env")
    assert "agent agent_0: action space Discrete(50) is not a Box" in msg
    assert "continuous_actions: true" in msg
    msg = refused(**{**REFERENCE, "success_key": "done_ok"})
    assert msg.startswith("success_key: 'done_ok' is in no agent's info after a step")
    assert "(info keys: at_goal)" in msg  # what the env does report
    assert refused(**REFERENCE, algo="ddpg").startswith("config: algo ddpg trains one agent")
    one = {"task": TINY, "task_kwargs": {"agents": 1}}
    assert "needs several agents" in refused(**one, algo="cen-maddpg")
    assert make_config({**one, "algo": "ddpg", "explore": "dis-macb"}).n_agents == 1
    assert refused(**REFERENCE, reward="sparse").startswith("reward: a custom task's reward")
    for key, value in [("cover", "landmark"), ("pad_obs", True), ("integrator", "velocity-first")]:
        assert refused(**REFERENCE, **{key: value}).startswith(f"{key}: an option of the built-in")
    assert refused(task="simple", algo="ddpg", success_key="x").startswith("success_key: only")
    assert refused(task="simple", algo="ddpg", task_kwargs={}).startswith("task_kwargs: only")
    assert refused(task="simpel").startswith("task: unknown task 'simpel'")
    cfg = make_config(REFERENCE)
    assert (cfg.reward, cfg.n_agents) == ("dense", 2)  # the env's own reward by default
    thesis = make_config({**REFERENCE, "profile": "thesis"})  # its non-world options only
    assert (thesis.success_terminal, thesis.warmup, thesis.cover) == (True, "random", "sum")


def test_spec_is_mpe2s_with_actions_in_minus_one_to_one():
    spec = task_spec_for(make_config(REFERENCE))
    assert [a.name for a in spec.agents] == ["agent_0", "agent_1"]
    assert spec.obs_dims == (21, 21) and spec.act_dims == (15, 15)
    assert all(a.act_low == (-1.0,) * 15 and a.act_high == (1.0,) * 15 for a in spec.agents)
    assert (spec.joint_obs_dim, spec.joint_act_dim) == (42, 30)
    env = make_task_for(make_config(REFERENCE))
    assert env.spec == spec
    env.close()


def test_actions_are_scaled_from_minus_one_to_one_onto_the_box():
    cfg = make_config({"task": TINY, "task_kwargs": {"low": -2.0, "high": 4.0}})
    env = make_task_for(cfg, seed=0)
    env.reset()
    env.step_joint(np.array([-1.0, 1.0, 0.0, 0.5], np.float32))
    env.step_joint(np.array([-3.0, 7.0, -0.5, 1.0], np.float32))  # clipped to the box first
    sent = env._env.actions
    np.testing.assert_allclose(sent[0]["a0"], [-2.0, 4.0])
    np.testing.assert_allclose(sent[0]["a1"], [1.0, 2.5])
    np.testing.assert_allclose(sent[1]["a0"], [-2.0, 4.0])
    np.testing.assert_allclose(sent[1]["a1"], [-0.5, 4.0])
    assert sent[0]["a0"].dtype == np.float32
    env.close()


def test_early_ends_go_on_in_a_new_world_terminal_or_not():
    """Termination at step 3 is terminal (done 1), a truncation at step 2 is not; both
    go on in a fresh reset inside the episode, which stays episode_len long."""
    for kwargs, done_at in [({"terminate_at": 3}, 1.0), ({"truncate_at": 3}, 0.0)]:
        cfg = make_config({"task": TINY, "task_kwargs": kwargs, "episode_len": 5})
        env = make_task_for(cfg, seed=1)
        col = Collector(env, noise_sigma=0.1, seed=1)
        rows = [col.step(lambda o: np.zeros((len(o), 4), np.float32)) for _ in range(5)]
        assert [r.done for r in rows] == [0.0, 0.0, done_at, 0.0, 0.0]
        assert [r.episode_end for r in rows] == [False] * 4 + [True]
        assert env._env.resets == 2  # the first reset and the one after step 3
        # the row after the end starts from the new world, not from the ended one
        assert not np.allclose(rows[3].obs, rows[2].next_obs)
        assert col.episodes == 1
        env.close()


def test_success_comes_from_the_info_key_and_counts_in_evaluation():
    cfg = make_config(
        {"task": TINY, "task_kwargs": {"success_at": 2}, "success_key": "hit", "episode_len": 4}
    )
    envs = [make_task_for(cfg, seed=s) for s in range(2)]
    env = envs[0]
    env.reset()
    hits = [env.step_joint(np.zeros(4, np.float32)).success for _ in range(4)]
    assert hits == [False, True, False, False]
    res = evaluate(lambda o: np.zeros((len(o), 4), np.float32), envs, episodes=3)
    assert res.success_rate == 1.0 and res.steps == 12
    never = make_config({"task": TINY, "task_kwargs": {}, "success_key": "hit", "episode_len": 4})
    res = evaluate(lambda o: np.zeros((len(o), 4), np.float32), [make_task_for(never)], 2)
    assert res.success_rate == 0.0
    # the team reward is the mean of the agents' rewards (t and t + 1 at step t)
    env.reset()
    assert env.step_joint(np.zeros(4, np.float32)).reward == pytest.approx(1.5)


@pytest.mark.parametrize(
    "run",
    [
        {**REFERENCE, "algo": "dis-maddpg", "explore": "dis-macb"},
        {
            "task": "mpe2.simple_v3:parallel_env",
            "task_kwargs": {"continuous_actions": True, "max_cycles": 10},
            "episode_len": 10,
            "algo": "ddpg",
            "explore": "cen-macb",
        },
    ],
    ids=["dis-maddpg+dis-macb", "ddpg"],
)
def test_the_trainer_trains_a_custom_task(run, tmp_path):
    cfg = make_config({**run, **SMALL, "episodes": 6, "eval_every": 3, "learning_starts": 20})
    rows = train(cfg, tmp_path, progress=False)
    assert [r["episode"] for r in rows] == [3, 6]
    assert rows[-1]["env_steps"] == 60 and rows[-1]["counted_transitions"] == 60
    assert rows[-1]["updates"] == 40  # one per step after the 20 warm-up steps
    tables = 2 if cfg.explore == "dis-macb" and cfg.n_agents == 2 else 1
    assert rows[-1]["table_size"] >= tables  # every table got keys
    assert all(0.0 <= r["success_rate"] <= 1.0 for r in rows)
    assert json.loads((tmp_path / "config.json").read_text())["task"] == run["task"]


def test_macb_train_runs_a_custom_task_and_resumes_it(tmp_path):
    """Through the command: Cen-MADDPG with Cen-MACB on simple_reference. Then the run's
    newest cut is removed as if it had been killed after its cut at episode 6, and
    `--resume` gives the same rows (timing aside): the env's RNG is in the cut."""
    args = ["--task", REFERENCE["task"], "--task-kwargs", "{max_cycles: 10}"]
    args += ["--success-key", "at_goal", "--episode-len", "10", "--algo", "cen-maddpg"]
    args += ["--explore", "cen-macb", "--k", "32", "--hidden", "32,32", "--batch-size", "16"]
    args += ["--eval-episodes", "2", "--episodes", "8", "--eval-every", "2", "--seed", "3"]
    args += ["--learning-starts", "20", "--learner-lanes", "1"]
    out = tmp_path / "run"

    def macb_train(*more: str) -> subprocess.CompletedProcess:
        return macb("train", *more, "--quiet", "--cut-every", "0", check=True)

    proc = macb_train(*args, "--out", str(out))
    assert "done: 8 episodes" in proc.stdout
    rows = jsonl(out)
    assert [r["episode"] for r in rows] == [2, 4, 6, 8]
    assert [r["counted_transitions"] for r in rows] == [20, 40, 60, 80]
    assert [r["updates"] for r in rows] == [0, 20, 40, 60]  # one per step after 20
    cuts = sorted((out / "cuts").glob("cut-*.pt"))
    assert [c.name for c in cuts] == ["cut-000000006.pt", "cut-000000008.pt"]
    cuts[-1].unlink()
    macb_train("--resume", str(out))
    assert strip(jsonl(out)) == strip(rows)


TIMING = ("steps_per_sec", "train_steps_per_sec", "wall_s")


def strip(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIMING} for r in rows]


def jsonl(out) -> list[dict]:
    return [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]


def test_a_world_giving_a_nan_ends_macb_train_saying_where(tmp_path):
    """A custom task's NaN reward would go into replay and every update after it: the
    run ends at that step, naming the run and the field (the cluster's actor refuses
    to send such rows alike: the test below)."""
    from shared.run.rollout import WorldError

    cfg = make_config({"task": TINY, "task_kwargs": {"nan_at": 3}, "algo": "cen-maddpg",
                       "episodes": 2, "episode_len": 5, "eval_every": 1, **SMALL})  # fmt: skip
    with pytest.raises(WorldError, match="run out: its world gave a non-finite rew in episode 1"):
        train(cfg, tmp_path / "out", progress=False)


def test_the_cluster_and_its_api_run_a_custom_task(tmp_path):
    """Router, counter, learner, evaluator, an actor and the API as processes: a custom
    task goes in over HTTP like any other and is counted exactly once; bad ones get
    422 naming the field, the agent and the space, or the module the API may not import."""
    modules = '["mpe2", "pettingzoo", "examples", "tests"]'  # (tests.custom_envs too)
    with api_cluster(tmp_path, api_env={"MACB_API_TASK_MODULES": modules}) as cluster:
        url = cluster.url
        bad = httpx.post(
            f"{url}/experiments",
            json={"task": "mpe2.simple_reference_v3:parallel_env", "algo": "cen-maddpg"},
        )
        assert bad.status_code == 422, bad.text
        (err,) = bad.json()["detail"]
        assert err["field"] == "task"
        assert "agent agent_0: action space Discrete(50) is not a Box" in err["msg"]
        marker = tmp_path / "called"
        denied = httpx.post(
            f"{url}/experiments",
            json={"task": "os:system", "task_kwargs": {"command": f"touch {marker}"}},
        )
        assert denied.status_code == 422, denied.text
        (err,) = denied.json()["detail"]
        assert err["field"] == "task" and "module 'os' is not one this API" in err["msg"]
        assert not marker.exists(), "the factory was never called"
        episodes = 6
        body = {**REFERENCE, **SMALL, "algo": "cen-maddpg", "explore": "cen-macb"}
        body |= {"episodes": episodes, "eval_every": 3, "learning_starts": 20, "seeds": [0]}
        created = httpx.post(f"{url}/experiments", json=body)
        assert created.status_code == 201, created.text
        (run,) = created.json()["runs"]
        assert run["config"]["task"] == REFERENCE["task"] and run["config"]["reward"] == "dense"

        def done():
            r = httpx.get(f"{url}/runs/{run['id']}").json()
            return r if r["status"] in ("completed", "failed", "stopped") else None

        final = wait_for(done, timeout=240, interval=0.5, what="the custom-task run ended")
        assert final["status"] == "completed", final

        def counted():
            live = httpx.get(f"{url}/runs/{run['id']}").json()["live"]
            return live.get("counter", {}).get("counted_transitions") == episodes * 10

        wait_for(counted, timeout=10, what="the counter's final stats")
        points = httpx.get(f"{url}/runs/{run['id']}/metrics").json()["points"]
        assert [p["episode"] for p in points] == [3, 6]
        for p in points:
            assert p["env_steps"] == p["episode"] * 10
            # counted on collection, when the learner's bonus query came: actors run ahead
            assert p["env_steps"] <= p["counted_transitions"] <= episodes * 10
            assert 0.0 <= p["success_rate"] <= 1.0
        assert points[-1]["replay_ratio"] == pytest.approx(1.0)
        # `macb export` writes the cluster run's points as TensorBoard scalars
        tb = tmp_path / "tb"
        proc = macb("export", run["id"], "--api", url, "--tensorboard", str(tb), timeout=120)
        assert proc.returncode == 0, proc.stderr
        (folder,) = [p for p in tb.glob("*/*") if p.is_dir()]
        assert folder.name == "cen-maddpg_+_cen-macb-seed0"
        assert_same(read_back(folder), expected(points))
        print(f"custom task on the cluster: {[(p['episode'], p['success_rate']) for p in points]}")
        # A world giving a NaN reward: the actor refuses to send rows no learner takes
        # (resent and refused forever, the run never ended) and fails the run, saying so.
        nan = {**SMALL, "task": TINY, "task_kwargs": {"nan_at": 3}, "algo": "cen-maddpg"}
        nan |= {"episodes": 4, "episode_len": 5, "eval_every": 2, "seeds": [0]}
        created = httpx.post(f"{url}/experiments", json=nan)
        assert created.status_code == 201, created.text
        (run,) = created.json()["runs"]
        final = wait_for(done, timeout=120, interval=0.5, what="the NaN run ended")
        assert final["status"] == "failed", final
        assert "its steps gave rows no learner takes" in final["reason"], final
        assert "non-finite values in rew" in final["reason"], final
