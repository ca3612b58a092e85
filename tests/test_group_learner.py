"""GroupMADDPG: R runs stacked in one learner update as each would alone.

Each run of a group (its own seed, hence its own initial weights) is compared with a
BatchedMADDPG of the same spec fed the same batches: after every update the run's whole
state (weights, targets, Adam moments, update count) and its actions are equal, bit for
bit, in fp32 and (where the CPU has it) in bf16, for DDPG, Dis- and Cen-MADDPG, with one
minibatch per run or one per agent. A batch given to the wrong run is caught."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from shared.core.learners import AgentDims, BatchedMADDPG, LearnerSpec
from shared.core.learners.group import GroupMADDPG
from shared.core.learners.precision import native_bf16
from shared.envs.tasks import task_spec


def agents_of(task: str) -> list[AgentDims]:
    return [AgentDims(a.obs_dim, a.act_low, a.act_high) for a in task_spec(task).agents]


def batch(rng, agents, rows: int, per_agent: bool):
    n = len(agents)
    lead = (n, rows) if per_agent else (rows,)
    obs_dim = sum(a.obs_dim for a in agents)
    act_dim = sum(a.act_dim for a in agents)
    f = np.float32
    return (
        rng.standard_normal((*lead, obs_dim)).astype(f),
        rng.uniform(-1, 1, (*lead, act_dim)).astype(f),
        rng.standard_normal((*lead, n)).astype(f),
        rng.standard_normal((*lead, obs_dim)).astype(f),
        (rng.random(lead) < 0.2).astype(f),
    )


def assert_same_state(a: dict, b: dict, where: str) -> None:
    def walk(x, y, path):
        if isinstance(x, torch.Tensor):
            assert torch.equal(x, y), f"{where}: {path} differs"
        elif isinstance(x, dict):
            assert x.keys() == y.keys(), f"{where}: {path} keys"
            for k in x:
                walk(x[k], y[k], f"{path}.{k}")
        elif isinstance(x, list | tuple):
            assert len(x) == len(y)
            for k, (u, v) in enumerate(zip(x, y)):
                walk(u, v, f"{path}[{k}]")
        else:
            assert x == y, f"{where}: {path}: {x} != {y}"

    walk(a, b, "state")


PRECISIONS = ["fp32"] + (["bf16"] if native_bf16() else [])
CASES = [
    ("simple", "ddpg", False),
    ("speaker_listener", "dis-maddpg", False),
    ("speaker_listener", "cen-maddpg", False),
    ("speaker_listener", "cen-maddpg", True),
    ("spread", "dis-maddpg", True),
]


@pytest.mark.parametrize("rows", [13, 100])
@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("task,algo,per_agent", CASES)
def test_each_run_updates_as_alone(task, algo, per_agent, precision, rows):
    torch.set_num_threads(1)
    agents = agents_of(task)
    specs = [LearnerSpec(algo=algo, hidden=(64, 48), seed=s, same_init=s == 2) for s in (3, 1, 2)]
    group = GroupMADDPG(agents, specs, precision=precision)
    alone = [BatchedMADDPG(agents, s, precision=precision) for s in specs]
    rng = np.random.default_rng(0)
    for step in range(4):
        batches = [batch(rng, agents, rows, per_agent) for _ in specs]
        group.update(*(np.stack(cols) for cols in zip(*batches)))
        for learner, b in zip(alone, batches):
            learner.update(*b)
        obs = rng.standard_normal((3, 5, sum(a.obs_dim for a in agents))).astype(np.float32)
        acts = group.act(obs)
        for r, learner in enumerate(alone):
            assert_same_state(group.run_state_dict(r), learner.state_dict(), f"run {r} step {step}")
            np.testing.assert_array_equal(acts[r], learner.act(obs[r]))


def test_a_crossed_batch_is_caught():
    """Runs 0 and 1 given each other's batches: their states differ from alone."""
    agents = agents_of("speaker_listener")
    specs = [LearnerSpec(algo="cen-maddpg", hidden=(32, 32), seed=s) for s in (0, 1)]
    group = GroupMADDPG(agents, specs)
    alone = [BatchedMADDPG(agents, s) for s in specs]
    rng = np.random.default_rng(1)
    batches = [batch(rng, agents, 8, False) for _ in specs]
    group.update(*(np.stack(cols) for cols in zip(*batches[::-1])))
    for learner, b in zip(alone, batches):
        learner.update(*b)
    with pytest.raises(AssertionError):
        assert_same_state(group.run_state_dict(0), alone[0].state_dict(), "run 0")


def test_state_round_trip_continues_alike():
    agents = agents_of("speaker_listener")
    specs = [LearnerSpec(algo="cen-maddpg", hidden=(32, 32), seed=s) for s in (0, 1)]
    group = GroupMADDPG(agents, specs)
    rng = np.random.default_rng(2)
    for _ in range(3):
        group.update(*(np.stack(c) for c in zip(*[batch(rng, agents, 8, True) for _ in specs])))
    copy = GroupMADDPG(agents, specs)
    copy.load_run_state_dicts([group.run_state_dict(r) for r in range(2)])
    nxt = [batch(rng, agents, 8, True) for _ in specs]
    for g in (group, copy):
        g.update(*(np.stack(c) for c in zip(*nxt)))
    for r in range(2):
        assert_same_state(copy.run_state_dict(r), group.run_state_dict(r), f"run {r}")


@pytest.mark.parametrize("task,algo", [("simple", "ddpg"), ("speaker_listener", "cen-maddpg")])
def test_a_runs_actor_weights_are_those_of_its_learner_alone(task, algo):
    """What the evaluator loads for run r (read in place) equals run r's learner's own
    actor_weights, after updates, for every run of the group."""
    agents = agents_of(task)
    specs = [LearnerSpec(algo=algo, hidden=(32, 32), seed=s) for s in (0, 1, 2)]
    group = GroupMADDPG(agents, specs)
    rng = np.random.default_rng(4)
    for _ in range(2):
        group.update(*(np.stack(c) for c in zip(*[batch(rng, agents, 8, False) for _ in specs])))
    for r in range(3):
        mine = group.run_actor_weights(r)
        alone = group.run_learner(r).actor_weights()
        assert len(mine) == len(alone) == len(agents)
        for a, b in zip(mine, alone):
            assert_same_state(a, b, f"run {r}")
    assert not torch.equal(group.run_actor_weights(0)[0]["net.0.weight"],
                           group.run_actor_weights(1)[0]["net.0.weight"])  # fmt: skip
    # ... and loaded into another group's run, they act as there (an evaluator's group)
    other = GroupMADDPG(agents, [LearnerSpec(algo=algo, hidden=(32, 32), seed=9)] * 3)
    for r in range(3):
        other.load_run_actor_weights(r, group.run_actor_weights(r))
    obs = rng.standard_normal((3, 5, sum(a.obs_dim for a in agents))).astype(np.float32)
    assert np.array_equal(other.act(obs), group.act(obs))


def test_refuses_runs_that_cannot_share_an_update():
    agents = agents_of("simple")
    with pytest.raises(ValueError, match="lr_actor"):
        GroupMADDPG(agents, [LearnerSpec(algo="ddpg"), LearnerSpec(algo="ddpg", lr_actor=0.1)])
    group = GroupMADDPG(agents, [LearnerSpec(algo="ddpg", seed=s) for s in (0, 1)])
    with pytest.raises(ValueError, match="runs"):
        group.act(np.zeros((3, 4), np.float32))
    with pytest.raises(TypeError, match="per run"):
        group.state_dict()
