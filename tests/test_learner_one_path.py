"""The learner service's one path: a run alone is served as a group of one. Its
learner, wrapped (`SoloRuns`), must update and act exactly as on its own, and a run
alone resumes from its newest cut as before (the group rule, of one run)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from services.learner import checkpoint as ckpt
from shared.config import make_config
from shared.core.learners.runs import SoloRuns
from shared.core.replay import Batch, update_arrays
from shared.envs.tasks import task_spec_for
from shared.run.factories import build_learner
from tests.test_learner_parts import run
from tests.test_lockstep import state_differences

BASE = {"task": "speaker_listener", "hidden": [16, 16], "batch_size": 8, "learner_lanes": 1}


def minibatch(rng: np.random.Generator, obs: int, act: int, n: int) -> tuple[Batch, np.ndarray]:
    rows = 8
    f32 = lambda *shape: rng.normal(size=shape).astype(np.float32)  # noqa: E731
    done = (rng.random(rows) < 0.1).astype(np.float32)
    batch = Batch(obs=f32(rows, obs), act=f32(rows, act), rew=f32(rows), next_obs=f32(rows, obs),
                  done=done, idx=np.arange(rows))  # fmt: skip
    return batch, f32(rows, n)


@pytest.mark.parametrize("impl", ["reference", "batched"])
@pytest.mark.parametrize("minibatches", ["shared", "per-agent"])
def test_a_learner_as_a_group_of_one_updates_and_acts_as_on_its_own(impl: str, minibatches: str):
    cfg = make_config({**BASE, "learner_impl": impl, "minibatch": minibatches})
    spec = task_spec_for(cfg)
    own, inner = build_learner(cfg, spec), build_learner(cfg, spec)
    inner.load_state_dict(own.state_dict())
    one, rng = SoloRuns(inner), np.random.default_rng(0)
    per = spec.n_agents if minibatches == "per-agent" else 1
    for _ in range(3):
        drawn = [minibatch(rng, spec.joint_obs_dim, spec.joint_act_dim, spec.n_agents)
                 for _ in range(per)]  # fmt: skip
        cols = update_arrays([b for b, _ in drawn], [p for _, p in drawn])
        own.update(*cols)
        one.update(*[np.stack([c]) for c in cols])  # the group's columns: (1, ...)
    assert one.updates == own.updates == 3
    assert not state_differences(one.run_state_dict(0), own.state_dict())
    obs = rng.normal(size=(1, 1, spec.joint_obs_dim)).astype(np.float32)
    assert np.array_equal(one.act(obs)[:, 0], own.act(obs[0]))
    weights = one.run_actor_weights(0)
    assert all(torch.equal(a[k], b[k]) for a, b in zip(weights, own.actor_weights()) for k in a)


def test_a_run_alone_resumes_from_its_newest_cut_even_at_the_same_update(tmp_path):
    st = run(tmp_path)
    for episodes in (1, 2):  # two cuts in the warm-up: no update between them
        st.intake.episodes = episodes
        ckpt.write(st)
    fresh, loaded = run(tmp_path), []
    group = type("G", (), {"load_run_state_dicts": lambda self, s: loaded.extend(s)})()
    assert ckpt.restore(group, [fresh], print) == [2] and len(loaded) == 1
    nothing = run(tmp_path / "none")
    assert ckpt.restore(group, [nothing], print) == [None]  # no cut: the log alone
