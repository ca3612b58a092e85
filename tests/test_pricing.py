"""Pricing by slot: a row's slot in each count table, kept from when it was counted,
prices it later by a gather, giving the count that hashing its key again gives (a key's
slot never changes, counts only grow at collection); a group's minibatches come out of
one gather over its replay, each run's rows drawn from its own sampler. Checked against
the per-run way (sample, hash, look up, stack) on a group mixing every kind of arm."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cli.trainer import GroupRun
from shared.config import make_config
from shared.core.counting import CountSketch, CountTable
from shared.core.replay import fixed_update_arrays, update_arrays


def keys_of(rng: np.random.Generator, n: int, distinct: int, width: int = 4) -> np.ndarray:
    pool = rng.integers(0, 256, (distinct, width), dtype=np.uint8)
    return pool[rng.integers(0, distinct, n)]


def test_a_rows_slot_prices_it_as_its_key_does_while_counts_grow():
    rng = np.random.default_rng(0)
    table = CountTable(4)
    kept: list[tuple[np.ndarray, np.ndarray]] = []
    for size in (1, 7, 1, 300, 1, 2000, 1):  # grows past the first count array
        keys = keys_of(rng, size, 1500)
        slots = table.increment(keys)
        assert slots.dtype == np.int32 and slots.shape == (size,) and slots.min() >= 1
        kept.append((keys, slots))
        for k, s in kept:  # every row stored so far: the count of its key now
            assert np.array_equal(table.gather(s), table.counts(k))
            assert np.array_equal(table.slots(k), s)
    unseen = np.full((3, 4), 255, np.uint8)
    assert (
        np.array_equal(table.slots(unseen), [0, 0, 0])
        and not table.gather(table.slots(unseen)).any()
    )


def test_counting_in_batches_or_one_by_one_gives_the_same_table():
    rng = np.random.default_rng(1)
    keys = keys_of(rng, 3000, 800)
    one, batched = CountTable(4), CountTable(4)
    slots_one = np.concatenate([one.increment(keys[i : i + 1]) for i in range(len(keys))])
    slots_batched = np.concatenate(
        [batched.increment(keys[i : i + 500]) for i in range(0, 3000, 500)]
    )
    assert np.array_equal(slots_one, slots_batched)
    assert (one.count1, one.total, len(one)) == (batched.count1, batched.total, len(batched))
    k1, c1 = one.to_arrays(chunk=64)
    k2, c2 = batched.to_arrays()
    assert np.array_equal(k1, k2) and np.array_equal(c1, c2)
    true = {bytes(k): int(c) for k, c in zip(*np.unique(keys, axis=0, return_counts=True))}
    assert {bytes(k): int(c) for k, c in zip(k1, c1)} == true
    assert one.count1 == sum(c == 1 for c in true.values())


def test_a_table_read_back_keeps_every_slot():
    """to_arrays lists keys in slot order, so from_arrays gives each key its slot again
    (slots kept in a replay buffer across a snapshot still price right)."""
    rng = np.random.default_rng(2)
    table = CountTable(4)
    keys = keys_of(rng, 2500, 1200)
    slots = table.increment(keys)
    again = CountTable.from_arrays(*table.to_arrays(), total=table.total)
    assert np.array_equal(again.slots(keys), slots)
    assert np.array_equal(again.gather(slots), table.gather(slots))
    more = keys_of(rng, 50, 1200)
    assert np.array_equal(again.increment(more), table.increment(more))
    assert again.count1 == table.count1


def test_a_sketchs_slots_are_its_cells():
    rng = np.random.default_rng(3)
    sketch = CountSketch(4, width=64, depth=3, seed=5)
    keys = keys_of(rng, 400, 300)
    slots = sketch.increment(keys)
    assert slots.shape == (400, 3) and np.array_equal(slots, sketch.slots(keys))
    sketch.increment(keys_of(rng, 400, 300))
    assert np.array_equal(sketch.gather(slots), sketch.counts(keys))
    assert np.array_equal(
        sketch.gather(slots.reshape(4, 100, 3)), sketch.counts(keys).reshape(4, 100)
    )


ARMS = [
    {"explore": "cen-macb"},
    {"explore": "dis-macb", "count_sketch": {"width": 512, "depth": 3}},
    {"explore": "cen-macb", "bonus_at": "collection"},
    {"explore": "cen-macb", "hash": "none", "key": "state",
     "beta_schedule": {"kind": "linear", "end": 0.1, "horizon": 50, "unit": "episodes"}},
    {"explore": "constant"},
    {"explore": "none", "buffer_size": 150},
]  # fmt: skip


def filled_group(profile: str, replay_backend: str | None = None) -> GroupRun:
    cfgs = [
        make_config({"task": "speaker_listener", "algo": "cen-maddpg", "episodes": 50,
                     "hidden": [16, 16], "seed": r, "profile": profile, **arm})
        for r, arm in enumerate(ARMS)
    ]  # fmt: skip
    g = GroupRun(cfgs, [None] * len(cfgs), 60.0, replay_backend=replay_backend)
    for _ in range(260):  # past the smallest buffer's capacity: it wraps
        tr = g.collector.step(g.learner.act)
        for r, m in enumerate(g.members):
            m.collect(tr.obs[r], tr.act[r], float(tr.rew[r]), tr.next_obs[r],
                      float(tr.done[r]), int(tr.collisions[r]))  # fmt: skip
    return g


def per_run_arrays(g: GroupRun, rngs: list, live: list[bool]) -> list[np.ndarray]:
    """The update arrays as the per-run way made them: each run samples its minibatches,
    hashes their keys again and looks up its counts (a stored bonus as stored), and
    the parts are stacked."""
    k, size = g.minibatches_per_update, g.cfg.batch_size
    parts = []
    for m, rng, on in zip(g.members, rngs, live):
        if not on:
            parts.append(fixed_update_arrays(m.buffer, size, k, g.spec.n_agents))
            continue
        batches = [m.buffer.sample(size, rng) for _ in range(k)]
        bonuses = []
        for b in batches:
            if b.bonus is not None:
                bonuses.append(b.bonus)
                continue
            counts = m.explorer.counts(b.obs, b.act)
            bonus = m.explorer.bonus_from_counts(counts, len(b.rew), m.cfg.beta_at(m.env_steps))
            bonuses.append(bonus)
            m.diagnostics.record(bonus, counts)
        parts.append(update_arrays(batches, bonuses))
    return [np.stack(cols) for cols in zip(*parts)]


@pytest.mark.parametrize("profile", ["mpe2", "thesis"])  # one shared minibatch, one per agent
def test_the_group_step_gives_the_per_run_arrays_bit_for_bit(profile):
    g = filled_group(profile)
    live = [True, True, True, True, False, True]  # run 4 stopped by its rule: its fixed draw
    rngs = [np.random.default_rng([7, r]) for r in range(g.runs)]
    theirs = [np.random.default_rng([7, r]) for r in range(g.runs)]
    for m in g.members:  # (what collection recorded: bonus_at collection's diagnostics)
        m.diagnostics.take()
    for step in range(3):
        idx = g.replay.draw(g.cfg.batch_size, g.minibatches_per_update,
                            [r if on else None for r, on in zip(rngs, live)])  # fmt: skip
        got_diag = []
        bonuses = []
        for r, m in enumerate(g.members):
            bonuses.append(m.price(idx[r]) if live[r] else None)
            got_diag.append(m.diagnostics.take())
        ours = g.update_arrays(idx, bonuses, live)
        want = per_run_arrays(g, theirs, live)
        want_diag = [m.diagnostics.take() for m in g.members]
        assert len(ours) == len(want) == 5
        for name, x, y in zip(("obs", "act", "rew", "next_obs", "done"), ours, want):
            assert x.dtype == y.dtype and x.shape == y.shape, (step, name)
            assert np.array_equal(x, y), (step, name)
        assert got_diag == want_diag
        assert [r.bit_generator.state for r in rngs] == [r.bit_generator.state for r in theirs]
    assert g.members[0].diagnostics.n == 0 and got_diag[0]["bonus_mean"] > 0


@pytest.mark.parametrize("profile", ["mpe2", "thesis"])
def test_the_replay_on_a_device_gathers_the_hosts_arrays_bit_for_bit(profile):
    """The device backend (`GroupReplay` with torch tensors, forced here on the CPU): the
    same collection written in one copy per step, the same draws sent and gathered
    there, the bonuses priced on the host added there, a stopped run's fixed draw in
    its place: every update array equal to the host's, step after step, and every
    sampler and diagnostic as the host's leaves it."""
    host, dev = filled_group(profile), filled_group(profile, replay_backend="torch")
    assert dev.replay.backend == "torch" and not dev.replay.arrays
    # (not flushed by the fixture: the first gather writes all 260 steps' rows at once,
    # the wrapped buffer's rows more than once each, keeping each row's last)
    assert len(dev.replay.pending) == 260 * dev.runs
    assert all(isinstance(t, torch.Tensor) for t in dev.replay.tensors.values())
    with pytest.raises(ValueError, match="on a device"):
        dev.members[0].buffer.sample(4, np.random.default_rng(0))
    live = [True, True, True, True, False, True]
    rngs = {id(g): [np.random.default_rng([7, r]) for r in range(g.runs)] for g in (host, dev)}
    for g in (host, dev):
        for m in g.members:
            m.diagnostics.take()
    for step in range(3):
        got = {}
        for g in (host, dev):
            own = [r if on else None for r, on in zip(rngs[id(g)], live)]
            idx = g.replay.draw(g.cfg.batch_size, g.minibatches_per_update, own)
            bonuses = [m.price(idx[r]) if live[r] else None for r, m in enumerate(g.members)]
            got[id(g)] = (g.update_arrays(idx, bonuses, live),
                          [m.diagnostics.take() for m in g.members])  # fmt: skip
        (want, want_diag), (ours, our_diag) = got[id(host)], got[id(dev)]
        for name, x, y in zip(("obs", "act", "rew", "next_obs", "done"), ours, want):
            assert isinstance(x, torch.Tensor) and x.is_contiguous(), (step, name)
            assert x.numpy().dtype == y.dtype and x.shape == y.shape, (step, name)
            assert np.array_equal(x.numpy(), y), (step, name)
        assert our_diag == want_diag
        states = [[r.bit_generator.state for r in rngs[id(g)]] for g in (host, dev)]
        assert states[0] == states[1]
        # one more collected step, written in one copy for the group, between updates
        for g in (host, dev):
            tr = g.collector.step(g.learner.act)
            for r, m in enumerate(g.members):
                m.collect(tr.obs[r], tr.act[r], float(tr.rew[r]), tr.next_obs[r],
                          float(tr.done[r]), int(tr.collisions[r]))  # fmt: skip
            g.replay.flush()
    for k, v in host.replay.arrays.items():  # every stored row, the wrapped buffer's too
        assert np.array_equal(dev.replay.tensors[k].numpy().reshape(v.shape), v), k


def test_a_refilled_buffer_has_the_slots_counting_gave():
    """A resume refills the replay from its log: each row's slots found again by its key
    (the tables read back) are those its counting returned."""
    g = filled_group("mpe2")
    for m in g.members:
        n = len(m.buffer)
        again = m.slots_of(m.buffer.obs[:n], m.buffer.act[:n], chunk=37)
        assert len(again) == len(m.buffer.slots) == len(m.explorer.tables)
        for kept, found in zip(m.buffer.slots, again):
            assert np.array_equal(kept[:n], found)
