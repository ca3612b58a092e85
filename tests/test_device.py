"""The learner's torch device (`device` in the config): the engine builds, updates and
acts on it, checkpoints load anywhere, and a device this machine lacks is refused with
the reason before anything runs. Only the CPU is here to run on; a GPU user's path is
the same code with another device."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from shared.config import ConfigError, make_config
from shared.core.learners import BatchedMADDPG, LearnerSpec
from shared.core.learners.group import GroupMADDPG
from shared.core.learners.precision import DeviceError, resolve_device
from tests.harness import macb
from tests.test_group_learner import agents_of, assert_same_state, batch


def test_config_takes_device_names_and_refuses_others():
    assert make_config({"task": "simple", "algo": "ddpg"}).device == "cpu"
    assert make_config({"task": "simple", "algo": "ddpg", "device": "cuda:1"}).device == "cuda:1"
    with pytest.raises(ConfigError, match="device"):
        make_config({"task": "simple", "algo": "ddpg", "device": "gpu0"})
    with pytest.raises(ConfigError, match="device cuda needs learner_impl batched"):
        make_config({"task": "simple", "algo": "ddpg", "device": "cuda",
                     "learner_impl": "reference"})  # fmt: skip


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_a_missing_device_is_refused_with_the_reason():
    with pytest.raises(DeviceError, match="device cuda: not available here"):
        resolve_device("cuda")
    with pytest.raises(DeviceError):
        BatchedMADDPG(agents_of("simple"), LearnerSpec(algo="ddpg"), device="cuda")
    got = macb("train", "--task", "simple", "--algo", "ddpg", "--device", "cuda",
               "--episodes", "1", "--out", "/nonexistent/never", timeout=120)  # fmt: skip
    assert got.returncode == 2 and "device cuda: not available here" in got.stderr


def test_an_explicit_device_runs_the_same_update():
    """device='cpu' given explicitly (a torch.device too) is the default's update."""
    agents = agents_of("speaker_listener")
    specs = [LearnerSpec(algo="cen-maddpg", hidden=(32, 32), seed=s) for s in (0, 1)]
    a = GroupMADDPG(agents, specs)
    b = GroupMADDPG(agents, specs, device=torch.device("cpu"))
    rng = np.random.default_rng(0)
    bs = [batch(rng, agents, 8, True) for _ in specs]
    for g in (a, b):
        g.update(*(np.stack(c) for c in zip(*bs)))
    for r in range(2):
        state = b.run_state_dict(r)
        assert all(t.device.type == "cpu" for t in state["actors"][0].values())
        assert_same_state(a.run_state_dict(r), state, f"run {r}")
