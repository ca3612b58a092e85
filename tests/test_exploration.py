"""Dis-MACB and Cen-MACB receive the right vectors; counts change only on collection."""

import numpy as np
import pytest

from shared.core.exploration import BonusDiagnostics, CountExploration, ExploreSpec, constant_shift

# speaker_listener layout: speaker obs 3 / act 3, listener obs 11 / act 2
OBS, ACT = (3, 11), (3, 2)


def batch(n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.standard_normal((n, sum(OBS))), rng.uniform(-1, 1, (n, sum(ACT)))


def test_dis_tables_receive_each_agents_obs_and_action():
    ex = CountExploration(ExploreSpec(mode="dis-macb", k=64), OBS, ACT)
    obs, act = batch(5)
    v = ex.vectors(obs, act)
    assert len(v) == 2 and [x.shape[1] for x in v] == [6, 13]
    assert np.array_equal(v[0], np.concatenate([obs[:, :3], act[:, :3]], 1))
    assert np.array_equal(v[1], np.concatenate([obs[:, 3:], act[:, 3:]], 1))


def test_cen_table_receives_the_joint_vector():
    ex = CountExploration(ExploreSpec(mode="cen-macb", k=64), OBS, ACT)
    obs, act = batch(5)
    (v,) = ex.vectors(obs, act)
    assert v.shape == (5, 19)
    assert np.array_equal(v, np.concatenate([obs, act], 1))


def test_state_only_variant_drops_actions():
    cen = CountExploration(ExploreSpec(mode="cen-macb", key="state"), OBS, ACT)
    dis = CountExploration(ExploreSpec(mode="dis-macb", key="state"), OBS, ACT)
    obs, act = batch(4)
    assert np.array_equal(cen.vectors(obs, act)[0], obs)
    assert [x.shape[1] for x in dis.vectors(obs, act)] == [3, 11]


@pytest.mark.parametrize("mode", ["dis-macb", "cen-macb"])
@pytest.mark.parametrize("hash_", ["simhash", "none"])
def test_counts_after_t_transitions_sum_to_t_per_table(mode, hash_):
    ex = CountExploration(ExploreSpec(mode=mode, k=32, hash=hash_), OBS, ACT)
    T = 0
    for step in range(37):
        obs, act = batch(3, seed=step)
        ex.observe(obs, act)
        T += 3
    for table in ex.tables:
        _, counts = table.to_arrays()
        assert counts.sum() == T == table.total


def test_sampling_a_batch_a_thousand_times_changes_no_count():
    ex = CountExploration(ExploreSpec(mode="cen-macb", k=16), OBS, ACT)
    obs, act = batch(200)
    ex.observe(obs, act)
    before = [t.to_arrays()[1].copy() for t in ex.tables]
    for i in range(1000):
        idx = np.random.default_rng(i).integers(0, 200, 100)
        ex.bonus(obs[idx], act[idx])
    after = [t.to_arrays()[1] for t in ex.tables]
    assert all(np.array_equal(a, b) for a, b in zip(before, after))
    assert ex.stats()["counted_transitions"] == 200


def test_bonus_is_beta_over_sqrt_count_per_agent():
    ex = CountExploration(ExploreSpec(mode="dis-macb", beta=0.5, k=8), OBS, ACT)
    obs, act = batch(1)
    for _ in range(4):
        ex.observe(obs, act)  # agent tables both see this pair 4 times
    obs2, act2 = batch(1, seed=99)
    ex.observe(obs2, act2)
    b = ex.bonus(np.concatenate([obs, obs2]), np.concatenate([act, act2]))
    counts = ex.counts(np.concatenate([obs, obs2]), np.concatenate([act, act2]))
    assert b.shape == (2, 2)
    for i in range(2):
        assert np.allclose(b[:, i], 0.5 / np.sqrt(counts[i]))
    assert np.allclose(b[0], 0.5 / 2)  # n = 4 for both agents


def test_cen_bonus_is_shared_by_all_agents():
    ex = CountExploration(ExploreSpec(mode="cen-macb", beta=0.8, k=512), OBS, ACT)
    obs, act = batch(10)
    ex.observe(obs, act)
    b = ex.bonus(obs, act)
    assert b.shape == (10, 2)
    assert np.array_equal(b[:, 0], b[:, 1])
    assert np.allclose(b, 0.8)  # every key new at k=512


def test_none_and_constant_arms_do_not_count():
    obs, act = batch(7)
    none = CountExploration(ExploreSpec(mode="none", beta=0.8), OBS, ACT)
    const = CountExploration(ExploreSpec(mode="constant", beta=0.8), OBS, ACT)
    for ex in (none, const):
        ex.observe(obs, act)
        assert ex.tables == [] and ex.stats()["table_size"] == 0
    assert np.all(none.bonus(obs, act) == 0)
    assert np.allclose(const.bonus(obs, act), 0.8)


def test_bonus_for_an_uncounted_transition_is_refused():
    ex = CountExploration(ExploreSpec(mode="cen-macb", k=64), OBS, ACT)
    obs, act = batch(2)
    with pytest.raises(ValueError):
        ex.bonus(obs, act)


def test_count1_pct_matches_hand_count():
    ex = CountExploration(ExploreSpec(mode="cen-macb", hash="none"), OBS, ACT)
    obs, act = batch(3)
    ex.observe(obs[[0, 0, 1, 2, 2, 2]], act[[0, 0, 1, 2, 2, 2]])
    s = ex.stats()
    assert s["table_size"] == 3 and s["count1_pct"] == pytest.approx(100 / 3)


# ------------------------------------------------------------- bonus diagnostics
def test_bonus_diagnostics_mean_std_and_sampled_count1_since_the_last_point():
    d = BonusDiagnostics()
    d.record(np.array([[0.8, 0.8], [0.4, 0.4]]), [np.array([1, 4])])
    d.record(np.array([[0.8, 0.8]]), [np.array([0])])  # uncounted: priced as n = 1
    got = d.take()
    values = np.array([0.8, 0.8, 0.4, 0.4, 0.8, 0.8])
    assert got["bonus_mean"] == pytest.approx(values.mean())
    assert got["bonus_std"] == pytest.approx(values.std())
    assert got["sampled_count1_pct"] == pytest.approx(100 * 2 / 3)
    assert d.take() == {"bonus_mean": 0.0, "bonus_std": 0.0, "sampled_count1_pct": 0.0}


def test_bonus_diagnostics_std_is_exactly_zero_for_a_constant_shift():
    d = BonusDiagnostics()
    beta = np.float32(0.8)  # not exact in binary: sums of squares would leave residue
    for _ in range(1000):
        d.record(np.full((100, 2), beta), [np.ones(100, np.int64)])
    got = d.take()
    assert got["bonus_std"] == 0.0 and got["bonus_mean"] == pytest.approx(0.8)
    assert got["sampled_count1_pct"] == 100.0
    assert constant_shift([got, got])
    assert not constant_shift([])
    assert not constant_shift([got, {**got, "bonus_std": 0.01}])
    assert not constant_shift([{**got, "bonus_mean": 0.0}])  # no bonus is no shift


def test_bonus_diagnostics_of_several_tables_count_every_key():
    """Dis-MACB: one table per agent, so a row has one key per table."""
    d = BonusDiagnostics()
    d.record(np.zeros((2, 2)), [np.array([1, 2]), np.array([1, 1])])
    assert d.take()["sampled_count1_pct"] == 75.0


def test_hash_round_rounds_the_counted_vector_before_simhash():
    """`hash_round: 2` (the thesis code's Cen-MACB): vectors that round to the same
    2-decimal vector share a key; unrounded, a tiny difference changes the SimHash key
    whenever it flips a projection's sign, which over 200 pairs happens."""
    rng = np.random.default_rng(0)
    obs, act = batch(200)
    obs = np.round(obs, 2).astype(np.float32) + np.float32(0.001)
    nudged = obs + rng.uniform(-0.0009, 0.0009, obs.shape).astype(np.float32)
    rounded = CountExploration(ExploreSpec(mode="cen-macb", k=512, round=2), OBS, ACT)
    plain = CountExploration(ExploreSpec(mode="cen-macb", k=512), OBS, ACT)
    assert np.array_equal(rounded.keys(obs, act)[0], rounded.keys(nudged, act)[0])
    assert not np.array_equal(plain.keys(obs, act)[0], plain.keys(nudged, act)[0])
    rounded.observe(obs, act)
    assert (rounded.counts(nudged, act)[0] == 1).all()  # priced as the counted key


def test_hash_round_rounds_before_every_key_kind_and_sets_hash_nones_decimals():
    """The thesis code's Cen path rounds before whatever strategy keys the vector: with
    `hash: raw` the raw bytes are the rounded vector's; with `hash: none` the key is the
    vector at `hash_round` decimals (2 without it, the thesis's "decimals"), in keys wide
    enough for them."""
    from shared.core.simhash import RoundKey

    obs, act = batch(50)
    obs = np.round(obs, 3).astype(np.float32)
    nudged = obs + np.float32(0.0004)  # the same vector at 3 decimals
    raw = CountExploration(ExploreSpec(mode="cen-macb", hash="raw", round=3), OBS, ACT)
    plain = CountExploration(ExploreSpec(mode="cen-macb", hash="raw"), OBS, ACT)
    assert np.array_equal(raw.keys(obs, act)[0], raw.keys(nudged, act)[0])
    assert not np.array_equal(plain.keys(obs, act)[0], plain.keys(nudged, act)[0])
    three = CountExploration(ExploreSpec(mode="cen-macb", hash="none", round=3), OBS, ACT)
    two = CountExploration(ExploreSpec(mode="cen-macb", hash="none"), OBS, ACT)
    assert [h.decimals for h in three.hashers] == [3]
    assert [h.decimals for h in two.hashers] == [2]
    apart = obs + np.float32(0.002)  # another vector at 3 decimals
    assert not np.array_equal(three.keys(obs, act)[0], three.keys(apart, act)[0])
    big = np.full((1, 2), 300.0)  # 3e10 at 8 decimals: past int32
    assert not np.array_equal(RoundKey(2, 8).keys(big), RoundKey(2, 8).keys(big + 1))
    assert RoundKey(2, 8).key_bytes == 16 and RoundKey(2).key_bytes == 8
