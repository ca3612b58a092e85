"""`precision: bf16`: one bf16 update stays within bf16's rounding of the fp32 reference
update; the fallback on a CPU without native bf16; lanes and the tuner on bf16."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch

import shared.core.learners.layers as layers
from shared.config import make_config
from shared.core.learners import (
    AUTO_MODES,
    MADDPG,
    AgentDims,
    BatchedMADDPG,
    LearnerSpec,
    TunedMADDPG,
    precision,
)
from shared.core.learners.layers import relu_, relu_backward
from shared.core.learners.precision import native_bf16 as detect_native_bf16  # before patching
from shared.envs.tasks import task_spec
from shared.run.factories import build_learner

MOVE = ((-1.0, -1.0), (1.0, 1.0))
SPEAKER_LISTENER = [AgentDims(3, (0.0,) * 3, (1.0,) * 3), AgentDims(11, *MOVE)]
SPREAD2 = [AgentDims(12, *MOVE)] * 2
SIMPLE = [AgentDims(4, *MOVE)]
# (algo, agents, one minibatch per agent): the three tasks, with the thesis profile's
# per-agent minibatches on speaker_listener too. Hidden 400-300 as in the thesis: the
# length of the sums is where bf16's rounding grows.
CASES = {
    "simple-ddpg": ("ddpg", SIMPLE, False),
    "spread-dis": ("dis-maddpg", SPREAD2, False),
    "spread-cen": ("cen-maddpg", SPREAD2, False),
    "speaker_listener-cen": ("cen-maddpg", SPEAKER_LISTENER, False),
    "speaker_listener-cen-per-agent": ("cen-maddpg", SPEAKER_LISTENER, True),
}
HIDDEN = (400, 300)

# The tolerance (derived in test_one_bf16_update_stays_within_bf16_rounding_of_fp32).
U = 2.0**-8  # unit roundoff of bf16's 8-bit significand, rounding to nearest
LEVELS = 12  # products on the longest chain into a gradient (see the test)
GRAD_ERROR = 2 * U * math.sqrt(LEVELS)  # ~0.027: typical relative error of a gradient
SAFETY = 4.0  # what the typical-error estimate leaves out (see the test)
SLACK = 1e-5  # fp32 reference vs fp32 batched (tests/test_batched_equivalence.py)


@pytest.fixture(autouse=True)
def bf16_available(monkeypatch):
    """bf16 runs (slower) on any CPU: say it is native so the arithmetic is checked
    everywhere; one thread, as the learner's default (restored)."""
    monkeypatch.setattr(precision, "native_bf16", lambda: True)
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def batch(m: MADDPG, per_agent: bool = False, n: int = 100, seed: int = 0) -> tuple:
    rng = np.random.default_rng(seed)
    o, a = m.obs_off[-1], m.act_off[-1]
    lead = (m.n,) if per_agent else ()
    return (
        rng.standard_normal((*lead, n, o)).astype(np.float32),
        rng.uniform(-1, 1, (*lead, n, a)).astype(np.float32),
        rng.uniform(-1, 0, (*lead, n, m.n)).astype(np.float32),
        rng.standard_normal((*lead, n, o)).astype(np.float32),
        (rng.uniform(0, 1, (*lead, n)) < 0.2).astype(np.float32),
    )


def reference(case: str, warm: int) -> tuple[MADDPG, bool]:
    """The case's fp32 reference after `warm` updates of its own (Adam's moments warm)."""
    algo, agents, per_agent = CASES[case]
    ref = MADDPG(agents, LearnerSpec(algo=algo, hidden=HIDDEN, seed=1))
    for step in range(warm):
        ref.update(*batch(ref, per_agent, seed=100 + step))
    return ref, per_agent


def adam_factor(step: int, beta1: float = 0.9) -> float:
    """How much of a gradient's relative error reaches the Adam step of update `step`,
    in units of lr (see the test's docstring)."""
    return 2.0 if step == 1 else (1 - beta1) / (1 - beta1**step)


def misses(ref: MADDPG, low: BatchedMADDPG, ref_losses: dict, low_losses: dict) -> list[str]:
    """Where the bf16 learner's update is outside the tolerance of the reference's (both
    just made the same update from the same state); empty if within."""
    out = []
    spec, step = ref.spec, ref.updates
    ref_state, low_state = ref.state_dict(), low.state_dict()
    for key, lr in (("actors", spec.lr_actor), ("critics", spec.lr_critic)):
        for what, tensors, bound in (
            ("weights", key, 2 * lr),
            ("targets", f"{key[:-1]}_targets", 2 * spec.tau * lr),
        ):
            diff = torch.cat(
                [
                    (r[name] - f[name]).abs().flatten()
                    for r, f in zip(ref_state[tensors], low_state[tensors], strict=True)
                    for name in r
                    if name.startswith("net.")
                ]
            )
            if diff.max() > bound + SLACK:
                out.append(f"{key} {what}: max |diff| {diff.max():.3g} > {bound:.3g}")
            if what == "weights":
                mean_bound = SAFETY * adam_factor(step) * GRAD_ERROR * lr
                if diff.mean() > mean_bound:
                    out.append(f"{key}: mean |diff| {diff.mean():.3g} > {mean_bound:.3g}")
    # Relative errors of outputs after L products: 2u sqrt(L). Critic loss: Q (3
    # products) and y (6), squared; actor loss: Q(s, mu(s)) (6).
    loss_bounds = {
        "critic_loss": 2 * 2 * U * (math.sqrt(3) + math.sqrt(6)),
        "actor_loss": 2 * U * math.sqrt(6),
    }
    for name, rel in loss_bounds.items():
        err = abs(low_losses[name] - ref_losses[name])
        if err > rel * abs(ref_losses[name]) + SLACK:
            out.append(f"{name}: {low_losses[name]:.6g} vs {ref_losses[name]:.6g}, rel > {rel:.3g}")
    return out


def one_update(case: str, warm: int, **kw: object) -> tuple[MADDPG, BatchedMADDPG, dict, dict]:
    """The reference and a bf16 copy of it (`kw`: lanes=...), one update each on one batch."""
    ref, per_agent = reference(case, warm)
    low = BatchedMADDPG(ref.agents, ref.spec, precision="bf16", **kw)
    low.load_state_dict(ref.state_dict())
    b = batch(ref, per_agent, seed=7)
    return ref, low, ref.update(*b), low.update(*b)


@pytest.mark.parametrize("warm", [0, 3], ids=["fresh-adam", "warm-adam"])
@pytest.mark.parametrize("case", list(CASES))
def test_one_bf16_update_stays_within_bf16_rounding_of_fp32(case, warm):
    """One bf16 update against the fp32 reference's, from the same weights, Adam state
    and batch: every weight, every target and both losses within bf16's rounding.

    Rounding: bf16 keeps 8 significant bits, so an input rounded to it has relative
    error <= u = 2^-8 = 0.0039. A product's entry sum_k a_k b_k over K terms (K = the
    batch, 24, 400 or 300 here) then has error <= 2u per term; accumulated in fp32 (its
    own error ~K 2^-24, negligible), random term errors add up like sqrt(K) while the
    entry grows like sqrt(K) too, so its relative error is ~2u, plus u for rounding the
    output. Errors of successive products add in the same random way, so an output
    after L products is off by ~2u sqrt(L). The longest chain into a gradient has
    L = 12 products: a critic's (target actor and critic for y: 6, critic forward 3,
    backward 3) and an actor's (actor forward 3, critic forward 3, critic backward 3,
    actor backward 3), so a gradient is off by e = 2u sqrt(12) = 0.027 of its size.

    Weights: Adam moves a weight by lr m^/(sqrt(v^) + eps). At a fresh Adam (update 1)
    that is lr g/|g|, within lr whatever g, so |w_bf16 - w_fp32| <= 2 lr per weight,
    reached only where rounding flips the gradient's sign, a share ~e of them: the
    mean is <= 2 e lr. With moments from earlier updates the new gradient is a share
    (1 - b1)/(1 - b1^t) of m^ (0.29 at update 4) and barely moves v^: the mean is
    ~0.29 e lr and the 2 lr bound holds with room. The mean is bounded at 4x that
    estimate (SAFETY), for what it leaves out (sums that cancel, errors correlated
    along a chain): measured bf16 is 5x (actors, warm) to 200x below that bound.
    Targets move tau times their network's weights: <= 2 tau lr.

    Losses: the critic loss mean((Q - y)^2) with Q after 3 products and y after 6 is
    off by <= 2 (2u sqrt(3) + 2u sqrt(6)) of itself while |Q|, |y - r| <= |Q - y|, as
    early in training; the actor loss -mean Q(s, mu(s)) by 2u sqrt(6). These assume
    every row's error has the same sign, so no safety factor: bf16 is >= 25x below.

    test_much_worse_than_bf16_fails_the_check: the same check refuses products that
    keep 3 significand bits (fp8 e4m3's) or go through fp8 itself."""
    ref, low, ref_losses, low_losses = one_update(case, warm)
    assert misses(ref, low, ref_losses, low_losses) == []


def coarsen(keep_bits: int | None):
    """A cast that makes a bf16 tensor worse: its significand cut to `keep_bits` of
    bf16's 7 stored bits (low bits zeroed), or (None) rounded through fp8 e4m3."""

    def cast(x: torch.Tensor) -> torch.Tensor:
        if x.dtype != torch.bfloat16:
            return x
        if keep_bits is None:
            return x.to(torch.float8_e4m3fn).to(torch.bfloat16)
        mask = -(1 << (7 - keep_bits))  # int16 with the low 7 - keep_bits bits clear
        return torch.bitwise_and(x.view(torch.int16), mask).view(torch.bfloat16)

    return cast


@pytest.mark.parametrize("warm", [0, 3], ids=["fresh-adam", "warm-adam"])
@pytest.mark.parametrize("worse", [3, None], ids=["3-bit-significand", "fp8-e4m3"])
def test_much_worse_than_bf16_fails_the_check(monkeypatch, worse, warm):
    """The tolerance is tight enough to matter: the same learner whose products read
    inputs made worse than bf16 is caught by `misses`."""
    cast = coarsen(worse)
    forward, grad_input, grad_weight = (
        layers.linear_forward,
        layers.linear_grad_input,
        layers.linear_grad_weight,
    )
    monkeypatch.setattr(layers, "linear_forward", lambda x, w, b: forward(cast(x), cast(w), b))
    monkeypatch.setattr(layers, "linear_grad_input", lambda g, w: grad_input(cast(g), cast(w)))
    monkeypatch.setattr(
        layers, "linear_grad_weight", lambda g, x, dtype=None: grad_weight(cast(g), cast(x), dtype)
    )
    ref, low, ref_losses, low_losses = one_update("speaker_listener-cen", warm)
    assert misses(ref, low, ref_losses, low_losses) != []


@pytest.mark.parametrize("case", ["spread-dis", "speaker_listener-cen-per-agent"])
def test_bf16_on_two_lanes_stays_within_the_tolerance(case):
    """Lanes split the rows; each lane's products are bf16, their gradients summed in
    fp32: the same tolerance holds."""
    ref, low, ref_losses, low_losses = one_update(case, warm=3, lanes=2)
    assert misses(ref, low, ref_losses, low_losses) == []
    low.lanes.close()


@pytest.mark.parametrize("mode", AUTO_MODES, ids=[f"lanes{a}x{t}" for a, t in AUTO_MODES])
def test_every_tuner_mode_runs_bf16_within_the_tolerance(mode):
    """TunedMADDPG over a bf16 learner: each mode it may pick (one thread, two lanes,
    two torch threads) makes an update within the tolerance, and stats say bf16."""
    ref, per_agent = reference("speaker_listener-cen", warm=3)
    tuned = TunedMADDPG(
        BatchedMADDPG(ref.agents, ref.spec, lanes=2, precision="bf16"), modes=[mode]
    )
    tuned.load_state_dict(ref.state_dict())
    b = batch(ref, per_agent, seed=7)
    ref_losses, low_losses = ref.update(*b), tuned.update(*b)
    assert misses(ref, tuned.learner, ref_losses, low_losses) == []
    stats = tuned.stats()
    assert stats["bf16"] == 1.0 and stats[f"lanes{mode[0]}x{mode[1]}_share"] == 1.0


def test_fp32_state_and_fp32_acting():
    """Only the products are bf16: weights, targets and Adam's moments stay fp32 (and
    checkpoints the reference loads), acting uses the fp32 actors, and the actor weights
    shipped to actors and the evaluator are fp32."""
    ref, low, _, _ = one_update("speaker_listener-cen", warm=1)
    state = low.state_dict()
    for key in ("actors", "critics", "actor_targets", "critic_targets"):
        assert all(t.dtype == torch.float32 for sd in state[key] for t in sd.values())
    for key in ("actor_optims", "critic_optims"):
        moments = [t for sd in state[key] for s in sd["state"].values() for t in s.values()]
        assert all(t.dtype == torch.float32 for t in moments)
    ref.load_state_dict(state)
    obs = batch(ref, seed=3)[0]
    np.testing.assert_allclose(low.act(obs), ref.act(obs), rtol=0, atol=1e-6)
    assert all(t.dtype == torch.float32 for sd in low.actor_weights() for t in sd.values())
    assert low.act(obs).dtype == np.float32


def test_without_native_bf16_the_learner_runs_fp32_and_says_so(monkeypatch, caplog):
    """A CPU without avx512_bf16/amx_bf16: fp32, one warning, the stat says fp32; the
    update is the fp32 learner's bit for bit."""
    monkeypatch.setattr(precision, "native_bf16", lambda: False)
    spec = LearnerSpec(hidden=(32, 16), seed=2)
    with caplog.at_level(logging.WARNING, logger="macb.learners"):
        fallback = BatchedMADDPG(SPEAKER_LISTENER, spec, precision="bf16")
    warnings = [r for r in caplog.records if r.name == "macb.learners"]
    assert len(warnings) == 1 and "runs fp32" in warnings[0].getMessage()
    assert "avx512_bf16" in warnings[0].getMessage()
    assert fallback.precision == "fp32" and fallback.dtype == torch.float32
    assert fallback.stats()["bf16"] == 0.0
    plain = BatchedMADDPG(SPEAKER_LISTENER, spec)
    ref = MADDPG(SPEAKER_LISTENER, spec)
    b = batch(ref, seed=4)
    assert fallback.update(*b) == plain.update(*b)
    got, want = fallback.state_dict(), plain.state_dict()
    for key in ("actors", "critics", "actor_targets", "critic_targets"):
        for f, p in zip(got[key], want[key], strict=True):
            assert all(torch.equal(f[k], p[k]) for k in f)


def test_the_factory_builds_bf16_from_the_config_and_falls_back(monkeypatch, caplog):
    """`precision: bf16` reaches the learner `macb train` and the learner service build
    (tuned or with fixed lanes); without native bf16 the same config runs fp32."""
    for lanes in ("auto", 1):
        cfg = make_config(
            {
                "task": "speaker_listener",
                "hidden": [16],
                "precision": "bf16",
                "learner_lanes": lanes,
            }
        )
        learner = build_learner(cfg, task_spec(cfg.task, cfg.agents, cfg.episode_len))
        assert learner.stats()["bf16"] == 1.0
        learner.update(*batch(MADDPG(SPEAKER_LISTENER, LearnerSpec(hidden=(16,))), n=8))
    monkeypatch.setattr(precision, "native_bf16", lambda: False)
    with caplog.at_level(logging.WARNING, logger="macb.learners"):
        learner = build_learner(cfg, task_spec(cfg.task, cfg.agents, cfg.episode_len))
    assert learner.stats()["bf16"] == 0.0
    assert sum(r.name == "macb.learners" for r in caplog.records) == 1


def test_precision_must_be_known():
    with pytest.raises(ValueError, match="precision must be one of"):
        BatchedMADDPG(SPEAKER_LISTENER, LearnerSpec(hidden=(16,)), precision="fp16")


def test_cpu_flags_are_read_from_cpuinfo():
    text = (
        "processor\t: 0\nflags\t\t: fpu sse avx512f avx512_bf16\n\n"
        "processor\t: 1\nflags\t\t: fpu sse avx512f avx512_bf16\n"
    )
    assert "avx512_bf16" in precision.cpu_flags(text)
    assert precision.cpu_flags("processor\t: 0\nflags\t\t: fpu sse avx2\n") == {
        "fpu",
        "sse",
        "avx2",
    }
    assert isinstance(detect_native_bf16.__wrapped__(), bool)  # the real file, if any


def every_bf16() -> torch.Tensor:
    """Every bf16 value but the NaNs."""
    bits = torch.arange(-(2**15), 2**15, dtype=torch.int32).to(torch.int16)
    x = bits.view(torch.bfloat16)
    return x[~x.isnan()]


def test_bf16_relu_through_int16_is_relu():
    x = every_bf16()
    got = relu_(x.clone())
    assert torch.equal(got, x.relu())  # -0.0 == 0.0: values, not bits
    assert (got.view(torch.int16) >= 0).all()  # +0 only, never -0: relu_backward's premise
    f = torch.randn(100)
    assert torch.equal(relu_(f.clone()), f.relu())  # fp32: torch's own


def test_bf16_relu_backward_through_int16_is_threshold_backward():
    x = relu_(every_bf16())
    grad = every_bf16()[torch.randperm(x.numel(), generator=torch.Generator().manual_seed(0))]
    want = torch.ops.aten.threshold_backward(grad, x, 0.0)
    assert torch.equal(relu_backward(grad, x).view(torch.int16), want.view(torch.int16))
