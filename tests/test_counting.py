"""SimHash keys, count tables and the bonus: the method's arithmetic pinned down."""

import numpy as np
import pytest

from shared.core.counting import CountTable, count_bonus
from shared.core.simhash import RoundKey, SimHash


def test_simhash_is_deterministic_per_seed():
    v = np.random.default_rng(0).standard_normal((50, 19))
    a, b, c = SimHash(19, 64, seed=7), SimHash(19, 64, seed=7), SimHash(19, 64, seed=8)
    assert np.array_equal(a.keys(v), b.keys(v))
    assert not np.array_equal(a.keys(v), c.keys(v))


def test_simhash_codes_are_sign_of_projection():
    h = SimHash(3, 16, seed=1)
    v = np.array([[0.3, -1.0, 2.0], [0.0, 0.0, 0.0]])
    expected = np.sign(v @ h.A.T)
    assert np.array_equal(h.codes(v), expected)
    # The zero vector projects to exactly 0: its code is all zeros, not all -1.
    assert np.all(h.codes(v)[1] == 0)
    neg = np.array([[-1e-3, -1e-3, -1e-3]])
    assert not np.array_equal(h.keys(v[1:]), h.keys(neg)), "0 and -1 must differ in the key"


def test_simhash_keys_pack_k_bits_compactly():
    h = SimHash(10, 512, seed=0)
    keys = h.keys(np.ones((4, 10)))
    assert keys.dtype == np.uint8 and keys.shape == (4, 2 * 64)


def test_near_vectors_share_codes_more_often_than_far_ones():
    rng = np.random.default_rng(3)
    h = SimHash(8, 32, seed=0)
    base = rng.standard_normal((2000, 8))
    near = base + 0.01 * rng.standard_normal(base.shape)
    far = rng.standard_normal(base.shape)
    same_near = np.mean(np.all(h.keys(base) == h.keys(near), axis=1))
    same_far = np.mean(np.all(h.keys(base) == h.keys(far), axis=1))
    assert same_near > 0.5
    assert same_far < 0.01
    # Bitwise agreement falls with angle, as SimHash promises.
    agree_near = np.mean(h.codes(base) == h.codes(near))
    agree_far = np.mean(h.codes(base) == h.codes(far))
    assert agree_near > 0.95 > 0.6 > agree_far


def test_roundkey_rounds_to_two_decimals():
    r = RoundKey(2)
    keys = r.keys(np.array([[0.123, -0.0], [0.1249, 0.0], [0.126, 0.0]]))
    assert np.array_equal(keys[0], keys[1])
    assert not np.array_equal(keys[0], keys[2])


def test_table_counts_and_count1_match_a_hand_count():
    t = CountTable(2)
    keys = np.array([[1, 0], [2, 0], [1, 0], [3, 0], [1, 0], [2, 0], [4, 0]], np.uint8)
    t.increment(keys)
    # hand count: key1 x3, key2 x2, key3 x1, key4 x1 -> 4 keys, 2 seen once
    assert len(t) == 4 and t.total == 7
    assert t.count1 == 2 and t.count1_pct == pytest.approx(50.0)
    assert t.counts(np.array([[1, 0], [2, 0], [3, 0], [9, 9]], np.uint8)).tolist() == [3, 2, 1, 0]


def test_lookups_never_change_counts():
    t = CountTable(2)
    keys = np.random.default_rng(0).integers(0, 4, size=(100, 2)).astype(np.uint8)
    t.increment(keys)
    before = t.to_arrays()
    for _ in range(1000):
        t.counts(keys[:10])
    after = t.to_arrays()
    assert np.array_equal(before[0], after[0]) and np.array_equal(before[1], after[1])
    assert t.total == 100


def test_snapshot_round_trip():
    t = CountTable(4)
    t.increment(np.random.default_rng(1).integers(0, 3, size=(500, 4)).astype(np.uint8))
    keys, counts = t.to_arrays()
    u = CountTable.from_arrays(keys, counts, t.total)
    assert len(u) == len(t) and u.count1 == t.count1 and u.total == t.total
    assert np.array_equal(u.counts(keys), counts)


def test_bonus_is_beta_over_sqrt_n():
    b = count_bonus(np.array([1, 4, 9, 100]), beta=0.8)
    assert np.allclose(b, [0.8, 0.4, 0.8 / 3, 0.08])
    with pytest.raises(ValueError, match="never counted"):
        count_bonus(np.array([0, 1]), beta=0.8)
