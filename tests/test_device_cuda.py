"""The group learner on a CUDA device: what tests/test_device.py cannot show on torch's
`meta` device. A step that waits for the device (a host read, a blocking copy) fails
under sync-debug mode "error"; the update can be captured as one CUDA graph (what a
sync or a host-side branch on a device value would break); one update on the GPU
agrees with the CPU's within a stated tolerance (not bit for bit: the kernels differ).
Skipped, saying so, on a machine without CUDA (CI's, today)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from shared.core.learners import LearnerSpec
from shared.core.learners.group import GroupMADDPG, capture_update
from tests.test_group_learner import agents_of, batch

pytestmark = pytest.mark.skipif(
    not torch.cuda.is_available(),
    reason="no CUDA device here: the CUDA-only guards (sync-free, graph capture, "
    "CPU-vs-GPU agreement) need one",
)

TASK, ALGO, RUNS, ROWS = "speaker_listener", "cen-maddpg", 6, 100
LR = 1e-3  # LearnerSpec's default actor and critic learning rate


def make_group(device: str, precision: str = "fp32") -> GroupMADDPG:
    specs = [LearnerSpec(algo=ALGO, seed=s) for s in range(RUNS)]
    return GroupMADDPG(agents_of(TASK), specs, precision=precision, device=device)


def step(rng: np.random.Generator, per_agent: bool) -> list[np.ndarray]:
    """One group update's arrays, (R, ...) each."""
    bs = [batch(rng, agents_of(TASK), ROWS, per_agent) for _ in range(RUNS)]
    return [np.stack(c) for c in zip(*bs)]


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
@pytest.mark.parametrize("per_agent", [False, True], ids=["per-run", "per-agent"])
def test_update_and_act_never_wait_for_the_device(per_agent, precision):
    """Under sync-debug mode "error" any host wait raises: after a first update (it
    creates Adam's state), updates and `act_on_device` run without one."""
    g = make_group("cuda", precision)
    rng = np.random.default_rng(0)
    g.update(*step(rng, per_agent))
    arrays = [step(rng, per_agent) for _ in range(2)]
    obs = rng.standard_normal((RUNS, 1, g.joint_obs)).astype(np.float32)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for a in arrays:
            g.update(*a)
        actions = g.act_on_device(obs)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert actions.device.type == "cuda" and actions.shape == (RUNS, 1, g.joint_act)


def flat_weights(g: GroupMADDPG) -> torch.Tensor:
    """Every run's actor and critic weights, on the CPU, as one vector."""
    parts = []
    for r in range(g.runs):
        state = g.run_state_dict(r)
        for net in ("actors", "critics"):
            for layer in state[net]:
                parts += [t.detach().float().cpu().reshape(-1) for t in layer.values()]
    return torch.cat(parts)


def test_the_update_captures_as_one_cuda_graph_and_replays():
    """The update on device inputs, warmed up on a side stream, is captured as one
    graph; replaying it trains (the weights move and stay finite)."""
    g = make_group("cuda")
    rng = np.random.default_rng(1)
    graph = capture_update(g, g.tensors(*step(rng, True)))
    before = flat_weights(g)
    for _ in range(3):
        graph.replay()
    torch.cuda.synchronize()
    after = flat_weights(g)
    assert torch.isfinite(after).all()
    assert not torch.equal(before, after)


def test_one_update_on_the_gpu_agrees_with_the_cpu():
    """The same group and arrays on the CPU and on the GPU (fp32): actions before the
    update within 1e-5, losses within a relative 1e-3, and after one Adam step every
    weight within 2 x lr (a first Adam step moves a weight by at most lr, so a gradient
    near 0 of opposite signs on the two devices may differ by that), 99.9% within 1e-5."""
    cpu, gpu = make_group("cpu"), make_group("cuda")
    rng = np.random.default_rng(2)
    arrays = step(rng, True)
    obs = rng.standard_normal((RUNS, 4, cpu.joint_obs)).astype(np.float32)
    np.testing.assert_allclose(cpu.act(obs), gpu.act(obs), atol=1e-5, rtol=0)
    lc, lg = cpu.update(*arrays), gpu.update(*arrays)
    for name in ("critic_loss", "actor_loss"):
        assert lg[name] == pytest.approx(lc[name], rel=1e-3, abs=1e-6), name
    wc, wg = flat_weights(cpu), flat_weights(gpu)
    diff = (wc - wg).abs()
    assert float(diff.max()) <= 2 * LR * (1 + 1e-3)
    assert float((diff <= 1e-5).float().mean()) >= 0.999


def test_the_groups_replay_lives_on_the_gpu_and_its_step_never_waits():
    """A group built for CUDA keeps its replay there (`GroupReplay`'s torch backend).
    Under sync-debug mode "error", after a first update: storing a collection step's
    rows (one non-blocking copy from pinned memory), the draws and the bonuses (on the
    host) sent in one non-blocking copy, the gather, the sum and the update wait for
    nothing. `act`'s read of its actions, the one documented wait of a step, stays
    outside the guarded part."""
    from cli.trainer import GroupRun
    from shared.config import make_config
    from tests.test_pricing import ARMS

    cfgs = [
        make_config({"task": TASK, "algo": ALGO, "episodes": 50, "hidden": [32, 32],
                     "learning_starts": 0, "warmup": "policy", "device": "cuda", **arm})
        for arm in ARMS
    ]  # fmt: skip
    g = GroupRun(cfgs, [None] * len(cfgs), 60.0)
    assert g.replay.backend == "torch"
    assert {t.device.type for t in g.replay.tensors.values()} == {"cuda"}
    live = [r != 4 for r in range(g.runs)]  # run 4 stopped by its rule: its fixed draw

    def collect() -> None:
        tr = g.collector.step(g.learner.act)  # (reads the actions: the documented wait)
        torch.cuda.set_sync_debug_mode("error")
        try:
            for r, m in enumerate(g.members):
                m.collect(tr.obs[r], tr.act[r], float(tr.rew[r]), tr.next_obs[r],
                          float(tr.done[r]), int(tr.collisions[r]))  # fmt: skip
            g.replay.flush()
            rngs = [m.sample_rng if on else None for m, on in zip(g.members, live)]
            idx = g.replay.draw(g.cfg.batch_size, g.minibatches_per_update, rngs)
            bonuses = [m.price(idx[r]) if live[r] else None for r, m in enumerate(g.members)]
            arrays = g.update_arrays(idx, bonuses, live)
            assert all(a.device.type == "cuda" for a in arrays)
            g.learner.update(*arrays)
        finally:
            torch.cuda.set_sync_debug_mode("default")

    g.learner.update(*g.update_arrays(*first_step(g, live)))  # creates Adam's state
    torch.cuda.synchronize()
    for _ in range(3):
        collect()


def first_step(g, live: list[bool]) -> tuple:
    """One collected step and its draws, outside the guard (the first update's inputs)."""
    tr = g.collector.step(g.learner.act)
    for r, m in enumerate(g.members):
        m.collect(tr.obs[r], tr.act[r], float(tr.rew[r]), tr.next_obs[r],
                  float(tr.done[r]), int(tr.collisions[r]))  # fmt: skip
    rngs = [m.sample_rng if on else None for m, on in zip(g.members, live)]
    idx = g.replay.draw(g.cfg.batch_size, g.minibatches_per_update, rngs)
    return idx, [m.price(idx[r]) if live[r] else None for r, m in enumerate(g.members)], live
