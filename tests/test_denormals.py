"""`flush_denormals`: the learner's updates read and make subnormal floats as zero, in its
own thread, its lanes and torch's OpenMP threads, and nowhere else; off keeps IEEE
subnormals. (Why it exists: shared/core/learners/base.py, `denormals_flushed`.)"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from shared.config import make_config
from shared.core.learners import MADDPG, AgentDims, BatchedMADDPG, LearnerSpec, fused
from shared.core.learners.base import denormals_flushed
from shared.envs.tasks import task_spec
from shared.run.factories import build_learner

SUB = 1e-42  # a subnormal float32
MOVE = ((-1.0, -1.0), (1.0, 1.0))
SPEAKER_LISTENER = [AgentDims(3, (0.0,) * 3, (1.0,) * 3), AgentDims(11, *MOVE)]


def survives() -> bool:
    """Whether a subnormal survives arithmetic in this thread now."""
    return (torch.tensor([SUB]) * 1.0).item() != 0.0


def test_the_context_flushes_inside_only_and_nests():
    assert survives()
    with denormals_flushed(True):
        assert not survives()
        with denormals_flushed(True):
            assert not survives()
        assert not survives()  # the inner one left the outer's mode alone
    assert survives()
    with denormals_flushed(False):
        assert survives()


def batch(rows: int = 32, seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    f = np.float32
    return (
        rng.standard_normal((rows, 14)).astype(f),
        rng.uniform(-1, 1, (rows, 5)).astype(f),
        rng.uniform(-1, 0, (rows, 2)).astype(f),
        rng.standard_normal((rows, 14)).astype(f),
        np.zeros(rows, f),
    )


def padded_moments(m: BatchedMADDPG) -> torch.Tensor:
    """The speaker's first-layer actor weights on the padded input columns 3..10: their
    gradient is always exactly 0, so their Adam first moment only decays."""
    return m.actor_optim.state[m.actor.params[0]]["exp_avg"][0, :, 3:]


@pytest.mark.parametrize("lanes", [1, 2])
@pytest.mark.parametrize("flush", [True, False])
def test_a_subnormal_first_moment_is_flushed_by_an_update(flush, lanes):
    """The mechanism: a first moment of a zero-gradient weight, decayed to a subnormal,
    stays one under IEEE (0.9 x the value rounds back near it) and is 0 flushed."""
    spec = LearnerSpec(algo="cen-maddpg", hidden=(64, 64), flush_denormals=flush)
    m = BatchedMADDPG(SPEAKER_LISTENER, spec, lanes=lanes)
    m.update(*batch())
    padded_moments(m).fill_(SUB)
    m.update(*batch(seed=1))
    after = padded_moments(m)
    if flush:
        assert torch.all(after == 0)
    else:
        assert torch.all((after > 0) & (after < torch.finfo(torch.float32).tiny))
    assert survives()  # the caller's thread is as it was


def test_the_reference_learner_flushes_alike():
    spec = LearnerSpec(algo="cen-maddpg", hidden=(32, 32))
    ref = MADDPG(SPEAKER_LISTENER, spec)
    fast = BatchedMADDPG.from_reference(ref)
    for i in range(3):
        ref.update(*batch(seed=i)), fast.update(*batch(seed=i))
    a = ref.critic_optims[0].state_dict()["state"][0]["exp_avg"]
    b = fast.critic_optim.state[fast.critic.params[0]]["exp_avg"][0, :, : a.shape[1]]
    assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)


def test_the_config_key_reaches_the_learner():
    assert make_config({}).flush_denormals is True
    spec = task_spec("speaker_listener", 2)
    for value in (True, False):
        cfg = make_config({"task": "speaker_listener", "flush_denormals": value})
        learner = build_learner(cfg, spec)
        inner = getattr(learner, "learner", learner)  # TunedMADDPG wraps the batched one
        assert inner.spec.flush_denormals is value


def test_torchs_openmp_threads_flush_in_an_update_and_not_after():
    """torch's pool keeps its threads' mode; the context sets it in them (fused.py's
    library) and back. In a child: the pool must exist before the first update."""
    if fused.kernel() is None:
        pytest.skip("no C compiler: the pool is flushed only where an update starts it")
    code = textwrap.dedent(
        f"""
        import torch
        from shared.core.learners.base import denormals_flushed
        torch.set_num_threads(2)
        x = torch.full((1 << 22,), {SUB})
        (x * 1.0).sum()  # the pool exists now, in IEEE mode
        def kept():  # subnormals surviving in both threads' halves
            y = x * 1.0
            return bool(y[: 1 << 21].ne(0).all()), bool(y[1 << 21 :].ne(0).all())
        before = kept()
        with denormals_flushed(True):
            inside = kept()
        print(before, inside, kept())
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    ).stdout.split("\n")[-2]
    assert out == "(True, True) (False, False) (True, True)", out
