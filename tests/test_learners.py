"""The `Learner` protocol: every learner the factory can build satisfies it and, driven
through it alone, computes the same update."""

import numpy as np
import pytest
import torch

from shared.config import make_config
from shared.core.learners import (
    AUTO_MODES,
    MADDPG,
    AgentDims,
    BatchedMADDPG,
    Learner,
    LearnerSpec,
    TunedMADDPG,
    fused,
)
from shared.envs.tasks import task_spec_for
from shared.run.factories import build_learner

SPEAKER = AgentDims(3, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
LISTENER = AgentDims(11, (-1.0, -1.0), (1.0, 1.0))
SPEC = LearnerSpec(algo="cen-maddpg", hidden=(32, 16), seed=5)

# fp32 learners run Adam and the soft update in fused.py's kernel where it builds.
KERNEL = float(fused.kernel() is not None)


@pytest.fixture(autouse=True)
def one_thread():
    """The tuner sets torch's threads; put the process's setting back."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def batch(n=64, seed=0):
    rng = np.random.default_rng(seed)
    return (
        rng.standard_normal((n, 14)).astype(np.float32),
        rng.uniform(-1, 1, (n, 5)).astype(np.float32),
        rng.uniform(-1, 0, (n, 2)).astype(np.float32),
        rng.standard_normal((n, 14)).astype(np.float32),
        (rng.uniform(0, 1, n) < 0.2).astype(np.float32),
    )


def learners() -> dict[str, Learner]:
    agents = [SPEAKER, LISTENER]
    return {
        "reference": MADDPG(agents, SPEC),
        "batched": BatchedMADDPG(agents, SPEC),
        "tuned": TunedMADDPG(BatchedMADDPG(agents, SPEC, lanes=2), contended=lambda: False),
    }


def drive(learner: Learner, b) -> tuple[dict[str, float], np.ndarray, dict]:
    """One update and what a caller sees of it, through the protocol only."""
    losses = learner.update(*b)
    return losses, learner.act(b[0]), learner.state_dict()


def test_every_learner_satisfies_the_protocol_and_updates_alike():
    b = batch()
    seen = {}
    for name, learner in learners().items():
        assert isinstance(learner, Learner), name
        assert learner.updates == 0
        seen[name] = drive(learner, b)
        assert learner.updates == 1
        assert isinstance(learner.stats(), dict)
    ref_losses, ref_act, ref_state = seen["reference"]
    for name in ("batched", "tuned"):
        losses, act, state = seen[name]
        assert losses == pytest.approx(ref_losses, rel=1e-5, abs=1e-6), name
        np.testing.assert_allclose(act, ref_act, rtol=0, atol=1e-5)
        for key in ("actors", "critics", "actor_targets", "critic_targets"):
            for r, f in zip(ref_state[key], state[key], strict=True):
                assert r.keys() == f.keys()
                for k in r:
                    torch.testing.assert_close(f[k], r[k], atol=1e-5, rtol=0)
    # The tuner's first mode is one thread on one lane: the batched update exactly.
    assert seen["tuned"][0] == seen["batched"][0]
    np.testing.assert_array_equal(seen["tuned"][1], seen["batched"][1])


def test_actor_weights_and_checkpoints_move_through_the_protocol():
    made = learners()
    src = made["tuned"]
    src.update(*batch(seed=1))
    for name, dst in made.items():
        if dst is src:
            continue
        dst.load_actor_weights(src.actor_weights())
        np.testing.assert_allclose(dst.act(batch()[0]), src.act(batch()[0]), atol=1e-6)
        dst.load_state_dict(src.state_dict())
        assert dst.updates == src.updates == 1, name


def test_stats_say_how_the_update_runs():
    made = learners()
    assert made["reference"].stats() == {}
    assert made["batched"].stats() == {"lanes": 1.0, "bf16": 0.0, "fused": KERNEL}
    tuned = made["tuned"].stats()
    assert tuned["lanes"] == 1.0 and tuned["threads"] == 1.0 and tuned["bf16"] == 0.0
    assert tuned["contended_updates"] == 0 and tuned["contended_share"] == 0.0
    names = [
        f"{p}lanes{a}x{t}_{s}"
        for p in ("", "contended_")
        for a, t in AUTO_MODES
        for s in ("share", "update_ms")
    ]
    assert set(names) <= set(tuned)


def test_tuned_learner_needs_the_lanes_its_modes_use_and_batched_refuses_auto():
    with pytest.raises(ValueError, match="all 1 of the learner's"):
        TunedMADDPG(BatchedMADDPG([SPEAKER, LISTENER], SPEC))
    with pytest.raises(ValueError, match="TunedMADDPG"):
        BatchedMADDPG([SPEAKER, LISTENER], SPEC, lanes="auto")


@pytest.mark.parametrize(
    ("impl", "lanes", "kind"),
    [
        ("reference", "auto", MADDPG),
        ("batched", 2, BatchedMADDPG),
        ("batched", "auto", TunedMADDPG),
    ],
)
def test_factory_builds_what_the_config_asks_for(impl, lanes, kind):
    cfg = make_config(
        {"task": "speaker_listener", "hidden": [16], "learner_impl": impl, "learner_lanes": lanes}
    )
    calls = []
    learner = build_learner(cfg, task_spec_for(cfg), lambda: calls.append(1) or True)
    assert type(learner) is kind and isinstance(learner, Learner)
    learner.update(*batch(n=8))
    assert len(calls) == (kind is TunedMADDPG)
    if kind is TunedMADDPG:
        assert learner.stats()["contended_updates"] == 1
