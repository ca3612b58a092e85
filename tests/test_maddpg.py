"""The learner's structure and arithmetic, on tiny networks and random batches."""

import io

import numpy as np
import pytest
import torch

from shared.core.learners import MADDPG, AgentDims, LearnerSpec

SPEAKER = AgentDims(3, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
LISTENER = AgentDims(11, (-1.0, -1.0), (1.0, 1.0))


def make(algo="cen-maddpg", hidden=(16, 8), agents=(SPEAKER, LISTENER), **kw):
    return MADDPG(list(agents), LearnerSpec(algo=algo, hidden=hidden, seed=0, **kw))


def batch(m, n=32, seed=0):
    rng = np.random.default_rng(seed)
    o, a = m.obs_off[-1], m.act_off[-1]
    return (
        rng.standard_normal((n, o)).astype(np.float32),
        rng.uniform(0, 1, (n, a)).astype(np.float32),
        rng.uniform(-1, 0, (n, m.n)).astype(np.float32),
        rng.standard_normal((n, o)).astype(np.float32),
        np.zeros(n, np.float32),
    )


def params(modules):
    return [p.detach().clone() for m in modules for p in m.parameters()]


def changed(before, modules):
    return any(not torch.equal(a, b) for a, b in zip(before, params(modules)))


def test_centralized_critic_sees_everything_actors_only_their_own_obs():
    m = make("cen-maddpg")
    assert [c.net[0].in_features for c in m.critics] == [14 + 5, 14 + 5]
    assert [a.net[0].in_features for a in m.actors] == [3, 11]
    obs, act, *_ = batch(m, 4)
    o = torch.as_tensor(obs)
    a = torch.as_tensor(act)
    q = m.critics[0](o, a)
    o2 = o.clone()
    o2[:, 3:] += 1.0  # change only the listener's observation
    assert not torch.allclose(m.critics[0](o2, a), q), "speaker's critic must see listener obs"
    a2 = a.clone()
    a2[:, 3:] += 0.5  # change only the listener's action
    assert not torch.allclose(m.critics[0](o, a2), q), "speaker's critic must see listener act"
    act_before = m.act(obs)
    act_after = m.act(o2.numpy())
    assert np.allclose(act_before[:, :3], act_after[:, :3]), "speaker acts on its own obs only"
    assert not np.allclose(act_before[:, 3:], act_after[:, 3:])


def test_distributed_critic_sees_only_local_obs_and_action():
    m = make("dis-maddpg")
    assert [c.net[0].in_features for c in m.critics] == [6, 13]


def test_actions_stay_in_each_agents_box():
    m = make()
    obs = np.random.default_rng(0).standard_normal((100, 14)).astype(np.float32) * 100
    act = m.act(obs)
    assert act[:, :3].min() >= 0.0 and act[:, :3].max() <= 1.0
    assert act[:, 3:].min() >= -1.0 and act[:, 3:].max() <= 1.0


def np_mlp(net, x):
    layers = [mod for mod in net if isinstance(mod, torch.nn.Linear)]
    for j, lin in enumerate(layers):
        x = x @ lin.weight.detach().numpy().T + lin.bias.detach().numpy()
        if j < len(layers) - 1:
            x = np.maximum(x, 0)
    return x


@pytest.mark.parametrize("algo", ["cen-maddpg", "dis-maddpg"])
def test_critic_target_matches_hand_computation(algo):
    m = make(algo, hidden=(4,), gamma=0.9)
    obs, act, rew, nxt, done = batch(m, 6)
    done[2] = 1.0
    # Hand-computed target actions from target actors (tanh rescaled into the box).
    next_act = []
    for j, mu in enumerate(m.actor_targets):
        o = nxt[:, m.obs_off[j] : m.obs_off[j + 1]]
        lo, hi = np.array(m.agents[j].act_low), np.array(m.agents[j].act_high)
        next_act.append((hi + lo) / 2 + (hi - lo) / 2 * np.tanh(np_mlp(mu.net, o)))
    next_act = np.concatenate(next_act, 1)
    for i in range(2):
        if algo == "cen-maddpg":
            q_in = np.concatenate([nxt, next_act], 1)
        else:
            q_in = np.concatenate(
                [
                    nxt[:, m.obs_off[i] : m.obs_off[i + 1]],
                    next_act[:, m.act_off[i] : m.act_off[i + 1]],
                ],
                1,
            )
        q_next = np_mlp(m.critic_targets[i].net, q_in)[:, 0]
        y_hand = rew[:, i] + 0.9 * (1 - done) * q_next
        y = m.target_q(i, *m.tensors(rew, nxt, done)).numpy()
        assert np.allclose(y, y_hand, atol=1e-5)
        assert y[2] == pytest.approx(rew[2, i]), "no bootstrap through a terminal"


@pytest.mark.parametrize("algo", ["cen-maddpg", "dis-maddpg"])
def test_actor_update_of_agent_i_changes_only_agent_is_actor(algo):
    m = make(algo)
    obs, act, *_ = batch(m)
    for i in range(2):
        others = [m.actors[j] for j in range(2) if j != i]
        before_i, before_others = params([m.actors[i]]), params(others)
        before_critics = params(m.critics + m.critic_targets + m.actor_targets)
        m.actor_step(i, *m.tensors(obs, act))
        assert changed(before_i, [m.actors[i]])
        assert not changed(before_others, others)
        assert not changed(before_critics, m.critics + m.critic_targets + m.actor_targets)
        assert all(p.grad is None or p.grad.abs().sum() == 0 for p in m.critics[i].parameters())


def test_full_update_moves_targets_by_tau():
    m = make(tau=0.1)
    target_before = params(m.critic_targets)
    m.update(*batch(m))
    online = params(m.critics)
    for tb, ta, on in zip(target_before, params(m.critic_targets), online):
        assert torch.allclose(ta, 0.9 * tb + 0.1 * on, atol=1e-6)
    assert m.updates == 1


def test_ddpg_is_one_agent_only():
    with pytest.raises(ValueError, match="one agent"):
        make("ddpg")
    m = make("ddpg", agents=(LISTENER,))
    m.update(*batch(m))


def test_learning_reduces_critic_error_on_a_fixed_batch():
    m = make("cen-maddpg", hidden=(32, 32))
    b = batch(m, 64)
    first = m.update(*b)["critic_loss"]
    for _ in range(200):
        last = m.update(*b)["critic_loss"]
    assert last < 0.5 * first


def test_state_dict_loads_with_weights_only_and_restores_everything():
    m = make()
    for s in range(3):
        m.update(*batch(m, seed=s))
    buf = io.BytesIO()
    torch.save(m.state_dict(), buf)
    buf.seek(0)
    state = torch.load(buf, weights_only=True)
    m2 = make()
    m2.load_state_dict(state)
    assert m2.updates == 3
    obs = batch(m)[0]
    assert np.array_equal(m.act(obs), m2.act(obs))
    b = batch(m, seed=9)
    assert m.update(*b) == m2.update(*b), "optimizer state restored too"


def test_construction_is_seeded_and_leaves_the_global_rng_alone():
    """The same spec seed gives the same weights, and building a learner does not
    reseed the caller's torch RNG (it used to: torch.manual_seed in the constructor)."""
    agents = [AgentDims(4, (-1.0, -1.0), (1.0, 1.0))]
    torch.manual_seed(123)
    expected_next = torch.rand(3)
    torch.manual_seed(123)
    a = MADDPG(agents, LearnerSpec(algo="ddpg", hidden=(16, 16), seed=5))
    assert torch.equal(torch.rand(3), expected_next), "global RNG stream was disturbed"
    b = MADDPG(agents, LearnerSpec(algo="ddpg", hidden=(16, 16), seed=5))
    c = MADDPG(agents, LearnerSpec(algo="ddpg", hidden=(16, 16), seed=6))
    wa, wb, wc = (m.actors[0].state_dict() for m in (a, b, c))
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    assert not all(torch.equal(wa[k], wc[k]) for k in wa)
