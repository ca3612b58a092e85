"""The learners' fused master-weight kernel (shared/core/learners/fused.py, master.c):
its Adam, soft update and fp32 Adam-with-soft-update equal torch's bit for bit, a whole
fused update (bf16 and fp32, one run or a group) equals the unfused one bit for bit,
weights written between updates are cast anew, and where the kernel cannot be built the
learner says so and runs torch's ops."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import torch

from shared.core.learners import (
    AgentDims,
    BatchedMADDPG,
    LearnerSpec,
    TunedMADDPG,
    fused,
    precision,
)
from shared.core.learners.group import GroupMADDPG

MOVE = ((-1.0, -1.0), (1.0, 1.0))
CASES = {
    "simple-ddpg": ("ddpg", [AgentDims(4, *MOVE)], False),
    "spread-dis": ("dis-maddpg", [AgentDims(12, *MOVE)] * 2, False),
    "speaker_listener-cen": (
        "cen-maddpg",
        [AgentDims(3, (0.0,) * 3, (1.0,) * 3), AgentDims(11, *MOVE)],
        False,
    ),
    "speaker_listener-cen-per-agent": (
        "cen-maddpg",
        [AgentDims(3, (0.0,) * 3, (1.0,) * 3), AgentDims(11, *MOVE)],
        True,
    ),
}
# Sizes on both sides of torch's vector width (8) and cache line (16), and a layer's.
SIZES = [1, 2, 7, 8, 9, 15, 16, 17, 600, 120_003]


def test_the_kernel_shares_torchs_openmp_runtime(kernel):
    """One OpenMP runtime in the process: the kernel's libgomp is torch's (fused.py)."""
    maps = Path("/proc/self/maps").read_text().splitlines()
    gomp = {line.split()[-1] for line in maps if "libgomp" in line}
    assert len(gomp) == 1, gomp


@pytest.fixture(autouse=True)
def one_thread(monkeypatch):
    """bf16 counts as native (the arithmetic is checked on any CPU); one torch thread,
    where the kernel runs (restored after)."""
    monkeypatch.setattr(precision, "native_bf16", lambda: True)
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def kernel() -> fused.MasterKernel:
    k = fused.kernel()
    if k is None:
        pytest.skip(
            "no C compiler here: the fused kernel cannot be built (the learner runs unfused)"
        )
    return k


def moments(n: int, gen: torch.Generator) -> tuple[torch.Tensor, ...]:
    p = torch.randn(n, generator=gen) * 0.1
    g = torch.randn(n, generator=gen) * 1e-2
    m = torch.randn(n, generator=gen) * 1e-3
    v = torch.rand(n, generator=gen) * 1e-4
    return p, g, m, v


@pytest.mark.parametrize("grad_dtype", [torch.float32, torch.bfloat16], ids=["fp32", "bf16"])
@pytest.mark.parametrize("step", [1, 2, 7, 1000])
def test_adam_equals_torch_fused_adam_bit_for_bit(kernel, step, grad_dtype):
    gen = torch.Generator().manual_seed(step)
    tensors = [moments(n, gen) for n in SIZES]
    ours = [[t.clone() for t in ts] for ts in tensors]
    theirs = [[t.clone() for t in ts] for ts in tensors]
    grads = [ts[1].to(grad_dtype) for ts in tensors]
    lows = [torch.empty(n, dtype=torch.bfloat16) for n in SIZES]
    lr, beta1, beta2, eps = 1e-3, 0.9, 0.999, 1e-8
    kernel.adam(
        [o[0] for o in ours], grads, [o[2] for o in ours], [o[3] for o in ours], lows, step,
        lr, beta1, beta2, eps,
    )  # fmt: skip
    torch._fused_adam_(
        [t[0] for t in theirs],
        [g.float() for g in grads],
        [t[2] for t in theirs],
        [t[3] for t in theirs],
        [],
        [torch.tensor(float(step)) for _ in SIZES],
        amsgrad=False,
        lr=lr,
        beta1=beta1,
        beta2=beta2,
        weight_decay=0.0,
        eps=eps,
        maximize=False,
    )
    for n, o, t, low in zip(SIZES, ours, theirs, lows):
        for name, a, b in (("weight", o[0], t[0]), ("exp_avg", o[2], t[2]), ("sq", o[3], t[3])):
            assert torch.equal(a, b), f"{name} of a tensor of {n}: {(a - b).abs().max()}"
        assert torch.equal(low, t[0].bfloat16()), f"bf16 copy of a tensor of {n}"


@pytest.mark.parametrize("step", [1, 2, 1000])
def test_adam_soft_equals_torch_adam_then_lerp_bit_for_bit(kernel, step):
    """fp32: Adam, then each target's lerp towards its new weight, in one pass."""
    gen = torch.Generator().manual_seed(100 + step)
    tensors = [moments(n, gen) for n in SIZES]
    targets = [ts[0] + 0.05 * torch.randn(n, generator=gen) for ts, n in zip(tensors, SIZES)]
    ours = [[t.clone() for t in ts] for ts in tensors]
    theirs = [[t.clone() for t in ts] for ts in tensors]
    our_targets, their_targets = [t.clone() for t in targets], [t.clone() for t in targets]
    lr, beta1, beta2, eps, tau = 1e-2, 0.9, 0.999, 1e-8, 0.01
    kernel.adam_soft(
        [o[0] for o in ours], [o[1] for o in ours], [o[2] for o in ours], [o[3] for o in ours],
        our_targets, step, lr, beta1, beta2, eps, tau,
    )  # fmt: skip
    torch._fused_adam_(
        [t[0] for t in theirs], [t[1] for t in theirs], [t[2] for t in theirs],
        [t[3] for t in theirs], [], [torch.tensor(float(step)) for _ in SIZES],
        amsgrad=False, lr=lr, beta1=beta1, beta2=beta2, weight_decay=0.0, eps=eps,
        maximize=False,
    )  # fmt: skip
    torch._foreach_lerp_(their_targets, [t[0] for t in theirs], tau)
    for n, o, t, a, b in zip(SIZES, ours, theirs, our_targets, their_targets):
        for name, x, y in (("weight", o[0], t[0]), ("exp_avg", o[2], t[2]), ("sq", o[3], t[3])):
            assert torch.equal(x, y), f"{name} of a tensor of {n}: {(x - y).abs().max()}"
        assert torch.equal(a, b), f"target of a tensor of {n}: {(a - b).abs().max()}"


def test_soft_update_equals_torch_lerp_and_its_bf16_copy_bit_for_bit(kernel):
    gen = torch.Generator().manual_seed(0)
    params = [torch.randn(n, generator=gen) for n in SIZES]
    targets = [p + 0.1 * torch.randn(n, generator=gen) for p, n in zip(params, SIZES)]
    ours = [t.clone() for t in targets]
    lows = [torch.empty(n, dtype=torch.bfloat16) for n in SIZES]
    kernel.soft_update(ours, params, lows, 0.01)
    torch._foreach_lerp_(targets, params, 0.01)
    for n, a, b, low in zip(SIZES, ours, targets, lows):
        assert torch.equal(a, b), f"target of {n}"
        assert torch.equal(low, b.bfloat16()), f"bf16 copy of a target of {n}"


def test_bf16_copies_round_like_torch_on_ties_and_edge_values(kernel):
    """tau 0 leaves the targets as they are, so their copies are the conversion alone.
    A NaN stays a NaN; its bits are not compared (torch's own conversion gives 0xffff in
    its vector loop and 0x7fc0 in its scalar one). Infinities cannot pass a lerp."""
    tiny = torch.finfo(torch.float32).tiny
    values = torch.tensor(
        [
            1.0 + 2.0**-8,  # a tie: rounds to even (1.0)
            1.0 + 3 * 2.0**-8,  # a tie: rounds to even (up)
            1.0 + 2.0**-8 + 2.0**-20,  # just above a tie
            -(1.0 + 2.0**-8),
            tiny,
            tiny / 3,  # subnormal
            3.3895313892515355e38,  # the largest finite that stays finite
            0.0,
            1e-30,
            -7.25,
        ]
        * 2  # past the vector width, so both of torch's loops are met
    )
    targets = [values.clone()]
    lows = [torch.empty_like(values, dtype=torch.bfloat16)]
    kernel.soft_update(targets, [values.clone()], lows, 0.0)
    want = values.bfloat16().view(torch.int16)
    assert torch.equal(lows[0].view(torch.int16), want), (lows[0].view(torch.int16), want)
    nan = [torch.tensor([float("nan")] * 20)]
    kernel.soft_update([nan[0].clone()], nan, lows, 0.0)
    assert lows[0].isnan().all()


def test_the_kernel_refuses_what_it_cannot_read(kernel):
    p = [torch.zeros(4)]
    with pytest.raises(ValueError, match="contiguous CPU tensors of equal sizes"):
        kernel.adam(p, [torch.zeros(5)], [torch.zeros(4)], [torch.zeros(4)],
                    [torch.zeros(4, dtype=torch.bfloat16)], 1, 1e-3, 0.9, 0.999, 1e-8)  # fmt: skip
    with pytest.raises(ValueError, match="fp32"):
        kernel.adam([torch.zeros(4, dtype=torch.float64)], p, p, p,
                    [torch.zeros(4, dtype=torch.bfloat16)], 1, 1e-3, 0.9, 0.999, 1e-8)  # fmt: skip
    with pytest.raises(ValueError, match="tau < 0.5"):
        kernel.soft_update(p, p, [torch.zeros(4, dtype=torch.bfloat16)], 0.5)
    with pytest.raises(ValueError, match="must be fp32"):
        kernel.adam_soft(p, [torch.zeros(4, dtype=torch.bfloat16)], p, p, p, 1, 1e-3, 0.9,
                         0.999, 1e-8, 0.01)  # fmt: skip
    with pytest.raises(ValueError, match="tau < 0.5"):
        kernel.adam_soft(p, p, p, p, p, 1, 1e-3, 0.9, 0.999, 1e-8, 0.5)


def learner(
    case: str, fused_: bool | None, lanes: int = 1, precision: str = "bf16"
) -> BatchedMADDPG:
    algo, agents, _ = CASES[case]
    spec = LearnerSpec(algo=algo, hidden=(400, 300), seed=3)
    return BatchedMADDPG(agents, spec, lanes=lanes, precision=precision, fused=fused_)


def batch(m: BatchedMADDPG, per_agent: bool, seed: int, rows: int = 100) -> tuple:
    rng = np.random.default_rng(seed)
    lead = (m.n, rows) if per_agent else (rows,)
    f = np.float32
    return (
        rng.standard_normal((*lead, m.joint_obs)).astype(f),
        rng.uniform(-1, 1, (*lead, m.joint_act)).astype(f),
        rng.uniform(-1, 0, (*lead, m.n)).astype(f),
        rng.standard_normal((*lead, m.joint_obs)).astype(f),
        (rng.uniform(0, 1, lead) < 0.1).astype(f),
    )


def flat(state, prefix: str = ""):
    if isinstance(state, dict):
        for k, v in state.items():
            yield from flat(v, f"{prefix}/{k}")
    elif isinstance(state, (list, tuple)):
        for k, v in enumerate(state):
            yield from flat(v, f"{prefix}/{k}")
    else:
        yield prefix, state


def differences(a: BatchedMADDPG, b: BatchedMADDPG) -> list[str]:
    fa, fb = dict(flat(a.state_dict())), dict(flat(b.state_dict()))
    assert fa.keys() == fb.keys()
    return [
        k
        for k in fa
        if not (torch.equal(fa[k], fb[k]) if torch.is_tensor(fa[k]) else fa[k] == fb[k])
    ]


@pytest.mark.parametrize("precision", ["bf16", "fp32"])
@pytest.mark.parametrize("lanes", [1, 2])
@pytest.mark.parametrize("case", list(CASES))
def test_a_fused_update_equals_the_unfused_one_bit_for_bit(kernel, case, lanes, precision):
    plain, fast = learner(case, False, lanes, precision), learner(case, True, lanes, precision)
    assert fast.stats()["fused"] == 1.0 and plain.stats()["fused"] == 0.0
    per_agent = CASES[case][2]
    for i in range(4):
        b = batch(plain, per_agent, i)
        assert plain.update(*b) == fast.update(*b), f"losses of update {i}"
    assert differences(plain, fast) == []


def test_weights_written_between_updates_are_cast_anew(kernel):
    """The kernel keeps the bf16 copies from one update to the next; a checkpoint load or
    new actor weights must not be run on the old copies."""
    case = "speaker_listener-cen"
    a, other = learner(case, True), learner(case, True)
    for i in range(3):
        a.update(*batch(a, False, i))
        other.update(*batch(a, False, 10 + i))
    a.load_state_dict(other.state_dict())
    fresh = learner(case, False)
    fresh.load_state_dict(other.state_dict())
    b = batch(a, False, 99)
    assert a.update(*b) == fresh.update(*b)
    assert differences(a, fresh) == []

    a.load_actor_weights(other.actor_weights())
    fresh.load_actor_weights(other.actor_weights())
    b = batch(a, False, 100)
    assert a.update(*b) == fresh.update(*b)
    assert differences(a, fresh) == []


@pytest.mark.parametrize("precision", ["bf16", "fp32"])
def test_switching_torch_threads_between_updates_keeps_the_bits(kernel, precision):
    """The kernel splits large tensors over torch's threads (its OpenMP pool); the bits
    do not depend on the split, and a tuner switches threads block by block."""
    case = "spread-dis"
    plain, fast = learner(case, False, 1, precision), learner(case, True, 1, precision)
    try:
        for i, threads in enumerate([1, 2, 2, 1, 1, 2, 1]):
            torch.set_num_threads(threads)
            b = batch(plain, False, i)
            assert plain.update(*b) == fast.update(*b), f"update {i} on {threads} threads"
    finally:
        torch.set_num_threads(1)
    assert differences(plain, fast) == []


def test_the_tuner_runs_the_fused_learner(kernel):
    """The tuner switching torch's threads between blocks (one lane: the same sums as
    the plain learner run right after each update on the same threads)."""
    algo, agents, _ = CASES["spread-dis"]
    spec = LearnerSpec(algo=algo, hidden=(64, 64), seed=1)
    tuned = TunedMADDPG(BatchedMADDPG(agents, spec, precision="bf16"), modes=[(1, 1), (1, 2)])
    plain = BatchedMADDPG(agents, spec, precision="bf16", fused=False)
    try:
        for i in range(300):
            b = batch(plain, False, i, rows=32)
            assert tuned.update(*b) == plain.update(*b), f"update {i}"
    finally:
        torch.set_num_threads(1)
    stats = tuned.stats()
    assert stats["fused"] == 1.0
    assert stats["lanes1x1_share"] > 0 and stats["lanes1x2_share"] > 0  # both were run
    assert differences(tuned.learner, plain) == []


@pytest.fixture
def fresh_kernel_lookup(monkeypatch, tmp_path):
    """kernel() looked up anew (it is cached per process) in an empty cache directory."""
    monkeypatch.setenv("MACB_KERNEL_CACHE", str(tmp_path / "kernels"))
    fused.kernel.cache_clear()
    yield tmp_path / "kernels"
    fused.kernel.cache_clear()


def test_without_a_compiler_the_learner_runs_unfused_and_says_so(
    monkeypatch, caplog, fresh_kernel_lookup
):
    monkeypatch.setenv("CC", "no-such-compiler-here")
    with caplog.at_level(logging.WARNING, logger="macb.learners"):
        m = learner("simple-ddpg", None)
    assert m.stats()["fused"] == 0.0 and m.stats()["bf16"] == 1.0
    assert "no C compiler" in caplog.text
    with pytest.raises(ValueError, match="fused kernel cannot be built here"):
        learner("simple-ddpg", True)


def test_a_failing_build_is_reported_and_the_learner_runs_unfused(
    monkeypatch, caplog, tmp_path, fresh_kernel_lookup
):
    broken = tmp_path / "cc"
    broken.write_text("#!/bin/sh\n[ \"$1\" = --version ] && { echo broken 1.0; exit 0; }\n"
                      "echo 'cc: internal error' >&2; exit 1\n")  # fmt: skip
    broken.chmod(0o755)
    monkeypatch.setenv("CC", str(broken))
    with caplog.at_level(logging.WARNING, logger="macb.learners"):
        assert learner("simple-ddpg", None).stats()["fused"] == 0.0
    assert "could not be built" in caplog.text and "internal error" in caplog.text
    assert list(fresh_kernel_lookup.glob("*.so")) == []  # nothing half-written left


def test_macb_fused_0_turns_it_off(monkeypatch, fresh_kernel_lookup):
    monkeypatch.setenv("MACB_FUSED", "0")
    assert learner("simple-ddpg", None).stats()["fused"] == 0.0


def test_the_build_is_cached_by_source_compiler_and_flags(kernel, fresh_kernel_lookup):
    cc = fused._compiler()
    first = fused._build(cc)
    stamp = first.stat().st_mtime_ns
    assert fused._build(cc) == first and first.stat().st_mtime_ns == stamp  # not rebuilt
    assert [p.name for p in fresh_kernel_lookup.iterdir()] == [first.name]


@pytest.mark.parametrize("hidden", [(400, 300), (37, 5)], ids=["whole", "per-run"])
@pytest.mark.parametrize("per_agent", [False, True], ids=["shared", "per-agent"])
def test_a_fused_fp32_group_update_equals_the_unfused_one_bit_for_bit(kernel, hidden, per_agent):
    """A group's tensors go to the kernel whole or run by run (`_parts`: 37 x 5 weights
    are no whole number of vectors per run, so those go run by run, each with its own
    vector tail); either way every run's weights, moments and targets are torch's."""
    algo, agents, _ = CASES["speaker_listener-cen"]
    specs = [LearnerSpec(algo=algo, hidden=hidden, seed=s) for s in (1, 2, 3)]
    plain = GroupMADDPG(agents, specs, precision="fp32", fused=False)
    fast = GroupMADDPG(agents, specs, precision="fp32", fused=True)
    rng = np.random.default_rng(5)
    r, n, f = 3, plain.n, np.float32
    lead = (r, n, 64) if per_agent else (r, 64)
    for i in range(4):
        b = (
            rng.standard_normal((*lead, plain.joint_obs)).astype(f),
            rng.uniform(-1, 1, (*lead, plain.joint_act)).astype(f),
            rng.uniform(-1, 0, (*lead, n)).astype(f),
            rng.standard_normal((*lead, plain.joint_obs)).astype(f),
            (rng.uniform(0, 1, lead) < 0.1).astype(f),
        )
        assert plain.update(*b) == fast.update(*b), f"losses of update {i}"
    for run in range(r):
        assert differences(plain.run_learner(run), fast.run_learner(run)) == [], f"run {run}"


def test_fp32_steps_outside_update_leave_the_targets_to_soft_update(kernel):
    """The fp32 kernel soft-updates a network's targets in its Adam step only inside
    `update`: a caller stepping a critic itself sees the targets where they were until it
    calls `soft_update`, which then moves them (torch's lerp)."""
    m = learner("speaker_listener-cen", True, precision="fp32")
    assert m.stats()["fused"] == 1.0
    obs, act, rew, next_obs, done = m.tensors(*batch(m, False, 0))
    before = [t.clone() for t in m.critic.targets]
    m.critic_step(obs, act, m.target_q(rew, next_obs, done))
    assert all(torch.equal(a, b) for a, b in zip(before, m.critic.targets))
    m.soft_update()
    expected = [t.clone() for t in before]
    torch._foreach_lerp_(expected, m.critic.params, m.spec.tau)
    assert all(torch.equal(a, b) for a, b in zip(expected, m.critic.targets))


def test_the_kernel_is_for_the_cpu_only():
    with pytest.raises(ValueError, match="fused needs the CPU"):
        BatchedMADDPG(CASES["simple-ddpg"][1], LearnerSpec(algo="ddpg"), fused=True, device="meta")


def test_the_kernel_finds_torchs_vector_width_and_refuses_a_wrong_one(
    kernel, monkeypatch, caplog, fresh_kernel_lookup
):
    """Which of torch's two Adam loops an element goes through depends on torch's vector
    width; the kernel finds it by comparing with torch, and runs only where one matches."""
    assert kernel.vec in fused.VEC_WIDTHS
    monkeypatch.setattr(fused, "VEC_WIDTHS", (1,))  # every element in the vector loop
    with caplog.at_level(logging.WARNING, logger="macb.learners"):
        assert fused.kernel() is None
    assert "does not reproduce this torch's Adam bit for bit" in caplog.text
