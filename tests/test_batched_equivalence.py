"""BatchedMADDPG is the reference MADDPG update, batched: same numbers, update by update."""

import io

import numpy as np
import pytest
import torch

from shared.core.learners import (
    AUTO_MODES,
    MADDPG,
    AgentDims,
    BatchedMADDPG,
    LaneTuner,
    LearnerSpec,
    TunedMADDPG,
    fused,
)
from shared.core.networks import Actor, JointPolicy, weights_as_arrays

MOVE = ((-1.0, -1.0), (1.0, 1.0))
SPEAKER = AgentDims(3, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
LISTENER = AgentDims(11, *MOVE)
SIMPLE = [AgentDims(4, *MOVE)]
SPREAD2 = [AgentDims(12, *MOVE)] * 2
SPREAD3 = [AgentDims(18, *MOVE)] * 3
# Mixed sizes in an order where the first agent is not the widest, and a box that is
# not symmetric around zero, to exercise padding both ways.
MIXED = [AgentDims(5, (0.0, -2.0), (1.0, 3.0)), SPEAKER, LISTENER]

CASES = [
    ("cen-maddpg", [SPEAKER, LISTENER]),
    ("dis-maddpg", [SPEAKER, LISTENER]),
    ("cen-maddpg", SPREAD2),
    ("dis-maddpg", SPREAD2),
    ("cen-maddpg", SPREAD3),
    ("dis-maddpg", SPREAD3),
    ("ddpg", SIMPLE),
    ("cen-maddpg", MIXED),
    ("dis-maddpg", MIXED),
]
IDS = [f"{algo}-{len(agents)}x{agents[0].obs_dim}" for algo, agents in CASES]
ATOL = 1e-5
HIDDEN = (64, 48)

# fp32 learners run Adam and the soft update in fused.py's kernel where it builds.
KERNEL = float(fused.kernel() is not None)


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Tiny matrices: with 2 threads on 2 shared cores OpenMP waits dominate (restored)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def make(algo, agents, hidden=HIDDEN, **kw):
    return MADDPG(list(agents), LearnerSpec(algo=algo, hidden=hidden, seed=3, **kw))


def batch(m, n=100, seed=0):
    rng = np.random.default_rng(seed)
    o, a = m.obs_off[-1], m.act_off[-1]
    return (
        rng.standard_normal((n, o)).astype(np.float32),
        rng.uniform(-1, 1, (n, a)).astype(np.float32),
        rng.uniform(-1, 0, (n, m.n)).astype(np.float32),
        rng.standard_normal((n, o)).astype(np.float32),
        (rng.uniform(0, 1, n) < 0.2).astype(np.float32),
    )


def assert_same_state(ref_state, fast_state, atol=ATOL):
    assert ref_state["updates"] == fast_state["updates"]
    for key in ("actors", "critics", "actor_targets", "critic_targets"):
        for i, (r, f) in enumerate(zip(ref_state[key], fast_state[key], strict=True)):
            assert r.keys() == f.keys(), (key, i)
            for name in r:
                assert r[name].shape == f[name].shape, (key, i, name)
                torch.testing.assert_close(f[name], r[name], atol=atol, rtol=0, msg=f"{key}[{i}]")
    for key in ("actor_optims", "critic_optims"):
        for r, f in zip(ref_state[key], fast_state[key], strict=True):
            assert r["state"].keys() == f["state"].keys()
            for j in r["state"]:
                for k, v in r["state"][j].items():
                    torch.testing.assert_close(f["state"][j][k], v, atol=atol, rtol=0)


@pytest.mark.parametrize(("algo", "agents"), CASES, ids=IDS)
def test_batched_update_equals_per_agent_update(algo, agents):
    ref = make(algo, agents)
    fast = BatchedMADDPG.from_reference(ref)
    assert_same_state(ref.state_dict(), fast.state_dict(), atol=0)
    probe = batch(ref, seed=99)[0]
    for step in range(6):
        b = batch(ref, seed=step)
        ref_losses, fast_losses = ref.update(*b), fast.update(*b)
        for k in ("critic_loss", "actor_loss"):
            assert fast_losses[k] == pytest.approx(ref_losses[k], rel=1e-5, abs=1e-6)
        assert_same_state(ref.state_dict(), fast.state_dict())
        np.testing.assert_allclose(fast.act(probe), ref.act(probe), rtol=0, atol=ATOL)


@pytest.mark.parametrize(("algo", "agents"), CASES, ids=IDS)
@pytest.mark.parametrize(("lanes", "rows"), [(2, 100), (3, 7)])
def test_update_in_lanes_equals_per_agent_update(algo, agents, lanes, rows):
    """The minibatch split into row blocks computed in parallel threads, gradients summed:
    the same update as the reference (and as one lane) up to the order of additions.

    With 7 rows some gradients are ~1e-8, where Adam's step lr * m / (sqrt(v) + eps)
    turns rounding into differences up to ~2e-5 (one lane vs the reference shows it too,
    6e-6), still a fiftieth of one Adam step (lr 1e-3)."""
    atol = ATOL if rows >= 100 else 5e-5
    ref = make(algo, agents)
    one = BatchedMADDPG.from_reference(ref)
    fast = BatchedMADDPG(ref.agents, ref.spec, lanes=lanes)
    fast.load_state_dict(ref.state_dict())
    assert fast.lanes.blocks(rows) != [slice(0, rows)]  # really split
    for step in range(4):
        b = batch(ref, n=rows, seed=step)
        ref_losses, one_losses, fast_losses = ref.update(*b), one.update(*b), fast.update(*b)
        for k in ("critic_loss", "actor_loss"):
            assert fast_losses[k] == pytest.approx(ref_losses[k], rel=1e-5, abs=1e-6)
            assert fast_losses[k] == pytest.approx(one_losses[k], rel=1e-5, abs=1e-6)
        assert_same_state(ref.state_dict(), fast.state_dict(), atol)
        assert_same_state(one.state_dict(), fast.state_dict(), atol)
    fast.lanes.close()


def test_auto_modes_switch_and_stay_equal_to_the_reference():
    """TunedMADDPG (lanes 'auto'): the tuner runs blocks with one thread, two lanes and
    two torch threads; every update still equals the reference's."""
    ref = make("cen-maddpg", [SPEAKER, LISTENER])
    fast = TunedMADDPG(BatchedMADDPG(ref.agents, ref.spec, lanes=2))
    fast.load_state_dict(ref.state_dict())
    fast.tuner = LaneTuner(AUTO_MODES, block=2, probe_every=2)
    used = []
    try:
        for step in range(16):
            used.append(fast.tuner.choose())
            b = batch(ref, seed=step)
            ref.update(*b), fast.update(*b)
            if used[-1][1] == 2:
                assert torch.get_num_threads() == 2
            assert_same_state(ref.state_dict(), fast.state_dict())
    finally:
        torch.set_num_threads(1)
    assert set(used) == set(AUTO_MODES)
    stats = fast.stats()
    shares = [stats[f"lanes{a}x{t}_share"] for a, t in AUTO_MODES]
    assert sum(shares) == pytest.approx(1.0) and min(shares) > 0
    assert all(stats[f"lanes{a}x{t}_update_ms"] > 0 for a, t in AUTO_MODES)


def test_contended_updates_have_a_tuner_of_their_own():
    """An update while `contended()` says True is timed into its own tuner: the
    ordinary tuner's counts and estimates are untouched by it, stats() reports both,
    and every update still equals the reference's."""
    ref = make("cen-maddpg", [SPEAKER, LISTENER])
    now_contended = [False]
    fast = TunedMADDPG(
        BatchedMADDPG(ref.agents, ref.spec, lanes=2), contended=lambda: now_contended[0]
    )
    fast.load_state_dict(ref.state_dict())
    fast.tuner = LaneTuner([(1, 1)], block=2)
    fast.contended_tuner = LaneTuner([(2, 1)], block=2)
    flags = [step % 3 == 0 for step in range(12)]  # 4 contended, 8 ordinary
    for step, contended in enumerate(flags):
        b = batch(ref, seed=step)
        now_contended[0] = contended
        ref.update(*b), fast.update(*b)
        assert_same_state(ref.state_dict(), fast.state_dict())
    assert fast.tuner.chosen == {(1, 1): 8}
    assert fast.contended_tuner.chosen == {(2, 1): 4}
    stats = fast.stats()
    assert stats["contended_share"] == pytest.approx(4 / 12)
    assert stats["contended_updates"] == 4
    assert stats["lanes1x1_share"] == 1.0 and stats["contended_lanes2x1_share"] == 1.0
    assert stats["lanes1x1_update_ms"] > 0 and stats["contended_lanes2x1_update_ms"] > 0
    # A fixed lane count has no tuners (and takes no contended signal).
    one = BatchedMADDPG(ref.agents, ref.spec, lanes=1)
    one.load_state_dict(ref.state_dict())
    b = batch(ref, seed=99)
    ref.update(*b), one.update(*b)
    assert_same_state(ref.state_dict(), one.state_dict())
    assert one.stats() == {"lanes": 1.0, "bf16": 0.0, "fused": KERNEL}


def test_lanes_must_be_a_count():
    with pytest.raises(ValueError, match="lanes"):
        BatchedMADDPG([SPEAKER, LISTENER], LearnerSpec(hidden=HIDDEN), lanes="fast")
    with pytest.raises(ValueError, match="lanes"):
        BatchedMADDPG([SPEAKER, LISTENER], LearnerSpec(hidden=HIDDEN), lanes=0)


@pytest.mark.parametrize("algo", ["cen-maddpg", "dis-maddpg"])
def test_equal_at_the_thesis_network_size(algo):
    """Hidden 400-300 and batch 100: the sizes where the fast matrix layouts kick in."""
    ref = make(algo, [SPEAKER, LISTENER], hidden=(400, 300))
    fast = BatchedMADDPG.from_reference(ref)
    lanes = BatchedMADDPG(ref.agents, ref.spec, lanes=2)
    lanes.load_state_dict(ref.state_dict())
    for step in range(3):
        b = batch(ref, seed=step)
        ref.update(*b), fast.update(*b), lanes.update(*b)
    assert_same_state(ref.state_dict(), fast.state_dict())
    assert_same_state(ref.state_dict(), lanes.state_dict())


def test_adam_settings_travel_with_the_state():
    """Non-default Adam settings in a checkpoint are honoured (through optim.step())."""
    ref = make("cen-maddpg", [SPEAKER, LISTENER])
    for optim in ref.actor_optims + ref.critic_optims:
        optim.param_groups[0].update(weight_decay=0.01, amsgrad=True, lr=3e-3)
    fast = BatchedMADDPG.from_reference(ref)
    for step in range(3):
        b = batch(ref, seed=step)
        ref.update(*b), fast.update(*b)
        assert_same_state(ref.state_dict(), fast.state_dict())


def test_same_seed_gives_the_reference_initial_weights_without_touching_global_rng():
    agents = [SPEAKER, LISTENER]
    ref = make("cen-maddpg", agents)
    torch.manual_seed(123)
    expected_next = torch.rand(3)
    torch.manual_seed(123)
    fast = BatchedMADDPG(agents, LearnerSpec(algo="cen-maddpg", hidden=HIDDEN, seed=3))
    assert torch.equal(torch.rand(3), expected_next), "global RNG stream was disturbed"
    assert_same_state(ref.state_dict(), fast.state_dict(), atol=0)


def padded_entries(fast):
    """Every stored value in a padded (not any agent's) position: params, targets, Adam."""
    found = []
    for stack, optim in ((fast.actor, fast.actor_optim), (fast.critic, fast.critic_optim)):
        tensors = [stack.params, stack.targets]
        tensors += [[optim.state[p][k] for p in stack.params] for k in ("exp_avg", "exp_avg_sq")]
        for group in tensors:
            mask = [torch.ones_like(t, dtype=torch.bool) for t in group]
            for i in range(fast.n):
                for layer, (ins, outs) in enumerate(stack.index[i]):
                    mask[2 * layer][i][outs[:, None], ins] = False
                    mask[2 * layer + 1][i, 0, outs] = False
            found += [t[m] for t, m in zip(group, mask)]
    return torch.cat(found)


@pytest.mark.parametrize("algo", ["cen-maddpg", "dis-maddpg"])
def test_padding_stays_exactly_zero(algo):
    fast = BatchedMADDPG(MIXED, LearnerSpec(algo=algo, hidden=(16, 8)))
    for step in range(5):
        fast.update(*batch(fast, seed=step))
    pads = padded_entries(fast)
    assert pads.numel() > 0
    assert torch.count_nonzero(pads) == 0


@pytest.mark.parametrize("src_cls,dst_cls", [(BatchedMADDPG, MADDPG), (MADDPG, BatchedMADDPG)])
def test_checkpoints_move_between_implementations(src_cls, dst_cls):
    agents, spec = [SPEAKER, LISTENER], LearnerSpec(algo="cen-maddpg", hidden=(32, 16))
    src = src_cls(agents, spec)
    for s in range(3):
        src.update(*batch(src, seed=s))
    buf = io.BytesIO()
    torch.save(src.state_dict(), buf)
    buf.seek(0)
    dst = dst_cls(agents, LearnerSpec(algo="cen-maddpg", hidden=(32, 16), seed=7))
    dst.load_state_dict(torch.load(buf, weights_only=True))
    assert dst.updates == 3
    assert_same_state(src.state_dict(), dst.state_dict(), atol=0)
    b = batch(src, seed=9)
    src.update(*b), dst.update(*b)
    assert_same_state(src.state_dict(), dst.state_dict())


def test_state_dict_round_trip_continues_identically():
    agents, spec = SPREAD3, LearnerSpec(algo="cen-maddpg", hidden=(32, 16))
    a = BatchedMADDPG(agents, spec)
    for s in range(3):
        a.update(*batch(a, seed=s))
    buf = io.BytesIO()
    torch.save(a.state_dict(), buf)
    buf.seek(0)
    b = BatchedMADDPG(agents, spec)
    b.load_state_dict(torch.load(buf, weights_only=True))
    nb = batch(a, seed=5)
    assert a.update(*nb) == b.update(*nb), "optimizer state restored too"
    assert_same_state(a.state_dict(), b.state_dict(), atol=0)
    with pytest.raises(ValueError, match="checkpoint is for"):
        BatchedMADDPG(agents, LearnerSpec(algo="dis-maddpg")).load_state_dict(a.state_dict())
    with pytest.raises(ValueError, match="3 actors, learner has 2"):
        BatchedMADDPG(SPREAD2, spec).load_state_dict(a.state_dict())


@pytest.mark.parametrize("algo,agents", [("cen-maddpg", MIXED), ("ddpg", SIMPLE)])
def test_actor_weights_load_into_actor_and_act_the_same(algo, agents):
    fast = BatchedMADDPG(agents, LearnerSpec(algo=algo, hidden=(32, 16)))
    fast.update(*batch(fast))
    obs = batch(fast, seed=4)[0]
    weights = fast.actor_weights()
    expected = fast.act(obs)
    for i, (agent, sd) in enumerate(zip(agents, weights, strict=True)):
        actor = Actor(agent.obs_dim, agent.act_low, agent.act_high, (32, 16))
        actor.load_state_dict(sd)  # strict: exactly the Actor's keys and shapes
        got = actor(torch.as_tensor(obs[:, fast.obs_off[i] : fast.obs_off[i + 1]])).detach()
        np.testing.assert_allclose(
            got.numpy(), expected[:, fast.act_off[i] : fast.act_off[i + 1]], atol=1e-6
        )
    # What the learner service ships (weights_as_arrays of learner.actor_weights()).
    policy = JointPolicy(
        [a.obs_dim for a in agents],
        [a.act_low for a in agents],
        [a.act_high for a in agents],
        (32, 16),
    )
    policy.load(weights_as_arrays(fast.actor_weights()))
    np.testing.assert_allclose(policy(obs), expected, atol=1e-6)
    # Fresh tensors: training on does not change weights already handed out.
    before = {k: v.clone() for k, v in weights[0].items()}
    fast.update(*batch(fast, seed=1))
    assert all(torch.equal(before[k], weights[0][k]) for k in before)
    fast.load_actor_weights(weights)
    np.testing.assert_allclose(fast.act(obs), expected, atol=0)


def test_act_keeps_leading_shape_and_boxes():
    fast = BatchedMADDPG(MIXED, LearnerSpec(algo="cen-maddpg", hidden=(16,)))
    obs = np.random.default_rng(0).standard_normal((4, 5, fast.obs_off[-1])) * 100
    act = fast.act(obs.astype(np.float32))
    assert act.shape == (4, 5, fast.act_off[-1])
    assert fast.act(obs[0, 0].astype(np.float32)).shape == (fast.act_off[-1],)
    lows = np.concatenate([a.act_low for a in MIXED])
    highs = np.concatenate([a.act_high for a in MIXED])
    assert (act >= lows).all() and (act <= highs).all()


def test_rejects_what_the_reference_rejects():
    with pytest.raises(ValueError, match="algo must be"):
        BatchedMADDPG(SIMPLE, LearnerSpec(algo="maddpg"))
    with pytest.raises(ValueError, match="one agent"):
        BatchedMADDPG(SPREAD2, LearnerSpec(algo="ddpg"))


# ------------------------------------------------------ one minibatch per agent
def per_agent_batch(m, n=100, seed=0):
    """One minibatch per agent: every array with a leading agent axis (N, ...)."""
    parts = [batch(m, n=n, seed=seed * 10 + i) for i in range(m.n)]
    return tuple(np.stack([p[k] for p in parts]) for k in range(5))


@pytest.mark.parametrize(("algo", "agents"), CASES, ids=IDS)
@pytest.mark.parametrize("lanes", [1, 2])
def test_per_agent_minibatches_batched_equals_reference(algo, agents, lanes):
    """`minibatch: per-agent`: agent i learns from batch i alone; the batched learner
    (one lane or two) does what the reference's per-agent loop does."""
    ref = make(algo, agents)
    fast = BatchedMADDPG(ref.agents, ref.spec, lanes=lanes)
    fast.load_state_dict(ref.state_dict())
    for step in range(4):
        b = per_agent_batch(ref, seed=step)
        ref_losses, fast_losses = ref.update(*b), fast.update(*b)
        for k in ("critic_loss", "actor_loss"):
            assert fast_losses[k] == pytest.approx(ref_losses[k], rel=1e-5, abs=1e-6)
        assert_same_state(ref.state_dict(), fast.state_dict())


def test_per_agent_minibatches_mean_each_agent_learns_from_its_own():
    """Agent i's result depends on batch i only: changing batch j (j != i) leaves agent
    i's networks exactly as they were; the shared-batch update is the case where every
    agent's batch is the same."""
    base = make("cen-maddpg", SPREAD2)
    b = per_agent_batch(base, seed=1)
    other = tuple(x.copy() for x in b)
    other_parts = batch(base, seed=77)
    for k in range(5):
        other[k][1] = other_parts[k]  # a different batch for agent 1 only
    one, two = make("cen-maddpg", SPREAD2), make("cen-maddpg", SPREAD2)
    one.update(*b)
    two.update(*other)
    for key in ("actors", "critics"):
        s1, s2 = one.state_dict()[key], two.state_dict()[key]
        assert all(torch.equal(s1[0][n], s2[0][n]) for n in s1[0])  # agent 0 untouched
        assert not all(torch.equal(s1[1][n], s2[1][n]) for n in s1[1])  # agent 1 differs
    shared = batch(base, seed=5)
    same = tuple(np.stack([x] * base.n) for x in shared)
    a, c = make("cen-maddpg", SPREAD2), make("cen-maddpg", SPREAD2)
    a.update(*shared)
    c.update(*same)
    assert_same_state(a.state_dict(), c.state_dict(), atol=1e-6)


@pytest.mark.parametrize(("algo", "agents"), CASES, ids=IDS)
def test_same_init_gives_agents_of_one_shape_identical_weights(algo, agents):
    """`same_init` (the thesis code reseeds torch per agent): equal shapes start equal,
    in both learners alike; without it they differ."""
    ref = make(algo, agents, same_init=True)
    fast = BatchedMADDPG(ref.agents, ref.spec)
    assert_same_state(ref.state_dict(), fast.state_dict(), atol=0)
    plain = make(algo, agents).state_dict()
    sd = ref.state_dict()
    for i in range(1, len(agents)):
        if agents[i] == agents[0]:
            for key in ("actors", "critics"):
                assert all(torch.equal(sd[key][0][n], sd[key][i][n]) for n in sd[key][0])
                assert not all(torch.equal(plain[key][0][n], plain[key][i][n]) for n in sd[key][0])
