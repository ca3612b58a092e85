"""JointPolicy, the actor and evaluator's numpy forward pass, against the torch actors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from shared.core.networks import JointPolicy, actor_weights
from shared.envs.tasks import task_spec


def _policy(task: str = "speaker_listener", agents: int = 2) -> JointPolicy:
    spec = task_spec(task, agents)
    lows = [a.act_low for a in spec.agents]
    highs = [a.act_high for a in spec.agents]
    return JointPolicy(spec.obs_dims, lows, highs, (64, 48))


def _torch_forward(policy: JointPolicy, obs: np.ndarray) -> np.ndarray:
    o = torch.as_tensor(obs)
    b = policy.bounds
    with torch.no_grad():
        parts = [actor(o[..., b[i] : b[i + 1]]) for i, actor in enumerate(policy.actors)]
    return torch.cat(parts, -1).numpy()


@pytest.mark.parametrize(
    ("task", "agents"), [("simple", 1), ("spread", 3), ("speaker_listener", 2)]
)
@pytest.mark.parametrize("batch", [1, 10])
def test_numpy_forward_equals_the_torch_actors(task: str, agents: int, batch: int) -> None:
    torch.manual_seed(0)
    policy = _policy(task, agents)
    obs = np.random.default_rng(1).normal(size=(batch, policy.bounds[-1])).astype(np.float32)
    got = policy(obs)
    assert got.dtype == np.float32 and got.shape == (
        batch,
        sum(a.act_dim for a in task_spec(task, agents).agents),
    )
    np.testing.assert_allclose(got, _torch_forward(policy, obs), rtol=0, atol=2e-6)


def test_load_refreshes_the_numpy_weights_and_bad_weights_change_nothing() -> None:
    torch.manual_seed(0)
    policy, other = _policy(), _policy()
    obs = np.random.default_rng(2).normal(size=(4, policy.bounds[-1])).astype(np.float32)
    before = policy(obs)
    policy.load(actor_weights(other.actors))
    after = policy(obs)
    assert not np.allclose(before, after)  # the numpy copies follow the loaded weights
    np.testing.assert_allclose(after, _torch_forward(other, obs), rtol=0, atol=2e-6)
    # The box: speaker's message in [0, 1], listener's movement in [-1, 1].
    assert (after[:, :3] >= 0).all() and (after[:, :3] <= 1).all()
    assert (np.abs(after[:, 3:]) <= 1).all()

    bad = actor_weights(other.actors)
    bad[1]["net.0.weight"] = np.zeros((3, 3), np.float32)
    with pytest.raises(RuntimeError, match="size mismatch"):
        policy.load(bad)
    np.testing.assert_array_equal(policy(obs), after)  # what acts is still the last good load
    with pytest.raises(ValueError, match="weights for 1 agents"):
        policy.load(bad[:1])
    np.testing.assert_array_equal(policy(obs), after)
