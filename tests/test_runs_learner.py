"""R runs' learners behind one interface (`RunsLearner`, shared/core/learners/runs.py).

The trainer holds a run alone as a group of one: `SoloRuns` around the learner its config
builds, which must compute exactly what the learner does unwrapped. A group is one
`GroupMADDPG`, which shares the batched update with `BatchedMADDPG` rather than
inheriting it, so it offers no single-learner method it would have to refuse."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
import torch

from shared.core.learners import (
    MADDPG,
    BatchedMADDPG,
    LearnerSpec,
    RunsLearner,
    SoloRuns,
    TunedMADDPG,
)
from shared.core.learners import group as group_module
from shared.core.learners.group import GroupMADDPG
from tests.test_group_learner import agents_of, assert_same_state, batch

SPEC = LearnerSpec(algo="cen-maddpg", hidden=(32, 24), seed=4)


def learners():
    agents = agents_of("speaker_listener")
    return {
        "reference": MADDPG(agents, SPEC),
        "batched-lanes2": BatchedMADDPG(agents, SPEC, lanes=2),
        "tuned": TunedMADDPG(BatchedMADDPG(agents, SPEC, lanes=2)),
    }


@pytest.mark.parametrize("name", ["reference", "batched-lanes2", "tuned"])
def test_a_learner_as_a_group_of_one_computes_what_it_computes_alone(name):
    torch.set_num_threads(1)
    agents = agents_of("speaker_listener")
    plain, wrapped = learners()[name], SoloRuns(learners()[name])
    assert isinstance(wrapped, RunsLearner) and wrapped.runs == 1
    rng = np.random.default_rng(1)
    for step in range(3):
        arrays = batch(rng, agents, 16, per_agent=step == 1)
        plain.update(*arrays)
        wrapped.update(*(a[None] for a in arrays))
        assert_same_state(wrapped.run_state_dict(0), plain.state_dict(), f"step {step}")
    obs = arrays[0][None, :5]
    assert np.array_equal(wrapped.act(obs), plain.act(obs[0])[None])
    assert wrapped.updates == plain.updates == 3
    assert wrapped.run_learner(0) is wrapped.learner
    assert wrapped.stats() == plain.stats() or name == "tuned"  # a tuner's times differ

    other = SoloRuns(learners()[name])
    other.load_run_state_dicts([wrapped.run_state_dict(0)])
    assert_same_state(other.run_state_dict(0), plain.state_dict(), "loaded")
    other.load_run_actor_weights(0, wrapped.run_actor_weights(0))
    with pytest.raises(ValueError, match="runs"):
        wrapped.act(np.zeros((2, 5, obs.shape[-1]), np.float32))
    with pytest.raises(ValueError, match="states"):
        other.load_run_state_dicts([plain.state_dict()] * 2)
    with pytest.raises(IndexError):
        wrapped.run_learner(1)


def test_a_group_is_runs_learners_without_refusing_an_inherited_method():
    agents = agents_of("simple")
    group = GroupMADDPG(agents, [LearnerSpec(algo="ddpg", seed=s) for s in (0, 1)])
    assert isinstance(group, RunsLearner) and group.runs == 2
    assert not isinstance(group, BatchedMADDPG)
    assert not hasattr(group, "load_state_dict") and not hasattr(group, "actor_weights")
    assert "type: ignore[override]" not in inspect.getsource(group_module)
    one = group.run_learner(1)
    assert isinstance(one, BatchedMADDPG)
    assert_same_state(group.run_state_dict(1), one.state_dict(), "run 1")
