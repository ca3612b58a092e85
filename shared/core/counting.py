"""Count tables for SimHash (or rounded) keys, and the bonus beta / sqrt(n).

A table is only ever incremented with freshly *collected* training transitions;
look-ups (`counts`) never change it, so sampling a batch any number of times or
running evaluation episodes leaves the counts alone (thesis section 4.5.2: counting
at sample time makes the bonus vanish).
"""

from __future__ import annotations

import math
from itertools import islice
from typing import Any

import numpy as np


class CountTable:
    """A dictionary from packed keys (bytes) to slots, and each slot's visit count in one
    int64 array, with cheap summary stats.

    A key's slot is given when it is first counted and never changes (slots run 1, 2, ...
    in the order keys first arrive, the dictionary's order; slot 0 is every key never
    counted, its count always 0). `increment` returns each row's slot, so whoever stores
    a row can keep its slot and price it later by `gather`, an array look-up, rather than
    by hashing its key again: the count found is the same, as a row's key never changes.
    The counts are grown by replacing the array, never resized in place, and before any
    new slot is given out, so a reader on another thread reads valid (if stale) counts.
    """

    def __init__(self, key_bytes: int) -> None:
        self.key_bytes = key_bytes
        self._slots: dict[bytes, int] = {}
        self._n = np.zeros(1024, dtype=np.int64)  # _n[slot]; _n[0] = 0 (never counted)
        self.total = 0  # transitions counted
        self.count1 = 0  # keys seen exactly once

    def __len__(self) -> int:
        return len(self._slots)

    @property
    def slot_shape(self) -> tuple[int, ...]:
        """One row's slot: one int."""
        return ()

    def _split(self, keys: np.ndarray) -> list[bytes]:
        keys = np.ascontiguousarray(keys, dtype=np.uint8)
        if keys.ndim != 2 or keys.shape[1] != self.key_bytes:
            raise ValueError(f"expected (B, {self.key_bytes}) uint8 keys, got {keys.shape}")
        w = self.key_bytes
        raw = keys.tobytes()
        return [raw[i : i + w] for i in range(0, len(raw), w)]

    def _room(self, slots: int) -> None:
        """Counts for `slots` slots (0 included): a bigger copy when they do not fit."""
        n = self._n
        if slots > len(n):
            grown = np.zeros(max(slots, 2 * len(n)), dtype=np.int64)
            grown[: len(n)] = n
            self._n = grown

    def increment(self, keys: np.ndarray) -> np.ndarray:
        """Count each row once (a batch of collected transitions); each row's slot (B,)
        int32. How rows are batched changes nothing: count-1 is a function of the counts."""
        table = self._slots
        split = self._split(keys)
        self._room(len(table) + 1 + len(split))  # (before any new slot can be read)
        n = self._n
        get = table.get
        out = []
        for key in split:
            s = get(key)
            if s is None:
                s = table[key] = len(table) + 1
            out.append(s)
        if len(out) == 1:
            s = out[0]
            c = int(n[s]) + 1
            n[s] = c
            self.count1 += 1 if c == 1 else -1 if c == 2 else 0
        elif out:
            slots, times = np.unique(np.asarray(out, np.int64), return_counts=True)
            before = n[slots]
            after = before + times
            n[slots] = after
            self.count1 += int(np.count_nonzero(after == 1)) - int(np.count_nonzero(before == 1))
        self.total += len(out)
        return np.asarray(out, dtype=np.int32)

    def slots(self, keys: np.ndarray) -> np.ndarray:
        """Each row's slot (B,) int32, 0 for a key never counted; never modifies the table."""
        get = self._slots.get
        return np.fromiter((get(k, 0) for k in self._split(keys)), dtype=np.int32, count=len(keys))

    def gather(self, slots: np.ndarray) -> np.ndarray:
        """n now of the keys at these slots (any shape), int64: `counts` without the keys."""
        return self._n[slots]

    def counts(self, keys: np.ndarray) -> np.ndarray:
        """n(key) for each row, 0 for unseen keys; never modifies the table."""
        return self.gather(self.slots(keys))

    @property
    def count1_pct(self) -> float:
        """Share of keys seen exactly once, in percent (the thesis's count-1 percentage)."""
        return 100.0 * self.count1 / len(self._slots) if self._slots else 0.0

    def state_bytes(self) -> int:
        """About what a snapshot of the table writes: the keys and an int64 count each."""
        return len(self._slots) * (self.key_bytes + 8)

    def memory_bytes(self) -> int:
        """Approximate resident size: dict slots plus the key and int objects, and the
        count array."""
        import sys

        n = len(self._slots)
        if n == 0:
            return sys.getsizeof(self._slots) + self._n.nbytes
        some_key = next(iter(self._slots))
        return sys.getsizeof(self._slots) + n * (sys.getsizeof(some_key) + 28) + self._n.nbytes

    def to_arrays(self, chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:
        """(keys (n, key_bytes) uint8, counts (n,) int64) for a pickle-free snapshot, in
        slot order (the order keys first arrived).

        Built `chunk` keys at a time: in one piece the join is a C call that holds the
        GIL for the whole table (~0.17 s for a million 128-byte keys), stalling every
        other thread of the process (the counter answers bonus queries on another
        thread while it snapshots). The table must not change meanwhile (its one writer
        is the caller's thread).
        """
        n, w = len(self._slots), self.key_bytes
        keys = np.empty((n, w), dtype=np.uint8)
        counts = np.empty(n, dtype=np.int64)
        flat = keys.reshape(-1)
        key_it = iter(self._slots)
        for start in range(0, n, chunk):
            m = min(chunk, n - start)
            raw = b"".join(islice(key_it, m))
            flat[start * w : (start + m) * w] = np.frombuffer(raw, dtype=np.uint8)
            counts[start : start + m] = self._n[1 + start : 1 + start + m]
        return keys, counts

    @classmethod
    def from_arrays(cls, keys: np.ndarray, counts: np.ndarray, total: int) -> CountTable:
        table = cls(int(keys.shape[1]) if keys.ndim == 2 else 0)
        w = table.key_bytes
        raw = np.ascontiguousarray(keys, dtype=np.uint8).tobytes()
        table._slots = {raw[i * w : (i + 1) * w]: i + 1 for i in range(len(counts))}
        if len(table._slots) != len(counts):
            raise ValueError("a key appears twice in the snapshot")
        table._room(len(counts) + 1)
        table._n[1 : len(counts) + 1] = np.asarray(counts, dtype=np.int64)
        table.count1 = int(np.sum(counts == 1))
        table.total = int(total)
        return table


# The Carter-Wegman prime: a row's hash is (a . x + b) mod P over 16-bit words x of the
# key, then mod the width. a, b uniform in [0, P) make it pairwise independent.
SKETCH_PRIME = (1 << 31) - 1
SKETCH_MAX_WIDTH = 1 << 30  # width <= P / 2: the mod-width step keeps collisions <= 1/w + 1/P
SKETCH_MAX_DEPTH = 32
SKETCH_MAX_CELLS = 1 << 31  # 8 GiB of uint32 cells per table
_WORDS_PER_SUM = 1 << 15  # 2^15 * (2^16 - 1) * (2^31 - 2) < 2^63: no uint64 overflow
# A wave of fewer independent rows than this: the next rows go one by one instead.
_SEQUENTIAL_ROWS = 16


def sketch_shape(eps: float, delta: float) -> tuple[int, int]:
    """(width, depth) for count-min's bound: estimate <= true + eps * N with probability
    >= 1 - delta per key, width = ceil(e / eps), depth = ceil(ln(1 / delta))."""
    return math.ceil(math.e / eps), max(1, math.ceil(math.log(1.0 / delta)))


def sketch_bound(width: int, depth: int) -> tuple[float, float]:
    """(eps, delta) that a width x depth sketch guarantees: eps = e / width, delta =
    exp(-depth)."""
    return math.e / width, math.exp(-depth)


class CountSketch:
    """A count-min sketch in place of a `CountTable`: `depth` rows of `width` uint32
    cells, a key counted in one cell per row, its count the least of its cells.

    Memory is width x depth x 4 bytes whatever the number of keys. The estimate is never
    below the true count, and exceeds it by more than eps * N (N: transitions counted,
    eps = e / width) with probability at most delta = exp(-depth) per key.

    Conservative update (default): a key's cells are raised only to its new estimate
    (min + 1), not each by one. Every cell of a key stays >= its true count (so the
    lower bound holds) and no cell exceeds the plain sketch's (so the upper bound holds),
    and collisions inflate counts less. It is order-dependent: rows are applied in the
    order given, one by one in effect, so how they are batched never matters; the
    counter logs and replays them in the order it counted them.

    Hashes are Carter-Wegman over the key's 16-bit words (mod the prime 2^31 - 1,
    parameters from a numpy SeedSequence of `seed`): pairwise independent, the same in
    every process and on every platform (no Python `hash`). `__len__` and `count1` are
    estimates: a row whose estimate was 0 before it was counted is a new key, one whose
    estimate was 1 leaves the count-1 keys; a new key whose cells all collide is missed,
    so `len` never exceeds the true number of keys.
    """

    def __init__(
        self, key_bytes: int, width: int, depth: int, seed: int, conservative: bool = True
    ) -> None:
        if not 1 <= width <= SKETCH_MAX_WIDTH:
            raise ValueError(f"width: must be in [1, {SKETCH_MAX_WIDTH}], got {width}")
        if not 1 <= depth <= SKETCH_MAX_DEPTH:
            raise ValueError(f"depth: must be in [1, {SKETCH_MAX_DEPTH}], got {depth}")
        self.key_bytes = key_bytes
        self.width = width
        self.depth = depth
        self.seed = seed
        self.conservative = conservative
        self.cells = np.zeros((depth, width), dtype=np.uint32)
        words = (key_bytes + 1) // 2
        rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5EC7C4]))
        self._a = rng.integers(0, SKETCH_PRIME, size=(words, depth), dtype=np.uint64)
        self._b = rng.integers(0, SKETCH_PRIME, size=depth, dtype=np.uint64)
        self._rows = np.arange(depth, dtype=np.int64)
        self.total = 0  # transitions counted
        self._count1 = 0  # new keys less keys whose estimate left 1 (may run below 0)
        self._distinct = 0  # estimated keys (a lower bound)

    def __len__(self) -> int:
        return self._distinct

    @property
    def slot_shape(self) -> tuple[int, ...]:
        """One row's slot: its column in each of the `depth` rows."""
        return (self.depth,)

    def cells_of(self, keys: np.ndarray) -> np.ndarray:
        """Each key's column in each row: int64 (B, depth)."""
        keys = np.ascontiguousarray(keys, dtype=np.uint8)
        if keys.ndim != 2 or keys.shape[1] != self.key_bytes:
            raise ValueError(f"expected (B, {self.key_bytes}) uint8 keys, got {keys.shape}")
        if self.key_bytes % 2:
            keys = np.concatenate([keys, np.zeros((len(keys), 1), np.uint8)], axis=1)
        words = keys.view("<u2").astype(np.uint64)
        h = np.zeros((len(keys), self.depth), dtype=np.uint64)
        for s in range(0, words.shape[1], _WORDS_PER_SUM):
            part = words[:, s : s + _WORDS_PER_SUM] @ self._a[s : s + _WORDS_PER_SUM]
            h = (h + part % np.uint64(SKETCH_PRIME)) % np.uint64(SKETCH_PRIME)
        h = (h + self._b) % np.uint64(SKETCH_PRIME)
        return (h % np.uint64(self.width)).astype(np.int64)

    def increment(self, keys: np.ndarray) -> np.ndarray:
        """Count each row once, as if one by one in order (a batch of collected
        transitions); each row's slot, its cells (B, depth) int32 (`gather` prices it).
        Rows that touch no cell an earlier pending row touches do not depend on one
        another: they are counted at once, in waves; a short wave (a key repeated, cells
        shared) goes row by row instead."""
        slots = pending = self.cells_of(keys)
        while len(pending):
            free = _first_touches(pending, self.width)
            if free.all() or np.count_nonzero(free) >= _SEQUENTIAL_ROWS:
                self._apply(pending[free])
                pending = pending[~free]
            else:
                for i in range(min(_SEQUENTIAL_ROWS, len(pending))):
                    self._apply(pending[i : i + 1])
                pending = pending[_SEQUENTIAL_ROWS:]
        self.total += len(keys)
        return slots.astype(np.int32)

    def slots(self, keys: np.ndarray) -> np.ndarray:
        """Each row's cells (B, depth) int32: a sketch's slot of a key is its cells."""
        return self.cells_of(keys).astype(np.int32)

    def gather(self, slots: np.ndarray) -> np.ndarray:
        """The estimate now of the keys whose cells these are ((..., depth) -> (...))."""
        return self.cells[self._rows, slots].min(axis=-1).astype(np.int64)

    def _apply(self, cols: np.ndarray) -> None:
        """Count rows none of which shares a cell with another (so at once = in order)."""
        cur = self.cells[self._rows, cols]  # (m, depth)
        before = cur.min(axis=1)
        # conservative: raised to the new estimate; plain: each cell one more
        up = np.maximum(cur, (before + 1)[:, None]) if self.conservative else cur + np.uint32(1)
        self.cells[self._rows, cols] = up
        new = int(np.count_nonzero(before == 0))
        self._distinct += new
        self._count1 += new - int(np.count_nonzero(before == 1))

    def counts(self, keys: np.ndarray) -> np.ndarray:
        """The estimate n(key) >= the true count for each row; never modifies the sketch."""
        return self.gather(self.cells_of(keys))

    @property
    def count1(self) -> int:
        """Estimated keys seen exactly once (clamped here, never while counting, so that
        how rows are batched cannot change it)."""
        return min(max(self._count1, 0), self._distinct)

    @property
    def count1_pct(self) -> float:
        """Estimated share of keys seen exactly once, in percent."""
        return 100.0 * self.count1 / self._distinct if self._distinct else 0.0

    def state_bytes(self) -> int:
        """What a snapshot of the sketch writes: its cells."""
        return int(self.cells.nbytes)

    def memory_bytes(self) -> int:
        """Resident size: the cells and the hash parameters, whatever the keys."""
        return int(self.cells.nbytes + self._a.nbytes + self._b.nbytes)

    def state(self) -> dict[str, Any]:
        """The sketch as plain numbers and one int32 array (uint32 cells' bits)."""
        return {
            "cells": self.cells.view(np.int32).copy(),
            "total": self.total,
            "count1": self._count1,
            "distinct": self._distinct,
            "width": self.width,
            "depth": self.depth,
            "conservative": self.conservative,
        }

    def load_state(self, state: dict[str, Any]) -> None:
        """`state()`'s output back in place; ValueError naming what does not fit."""
        for name in ("width", "depth", "conservative"):
            if state[name] != getattr(self, name):
                raise ValueError(
                    f"{name} {state[name]} in the snapshot, {getattr(self, name)} here"
                )
        cells = np.asarray(state["cells"])
        if cells.shape != self.cells.shape or cells.dtype != np.int32:
            raise ValueError(
                f"cells {cells.dtype} {cells.shape}, expected int32 {self.cells.shape}"
            )
        self.cells = cells.view(np.uint32).copy()
        self.total = int(state["total"])
        self._count1 = int(state["count1"])
        self._distinct = int(state["distinct"])


def _first_touches(cols: np.ndarray, width: int) -> np.ndarray:
    """Which rows of `cols` touch no cell an earlier row touches (the first row always)."""
    depth = cols.shape[1]
    flat = (cols + np.arange(depth, dtype=np.int64) * width).reshape(-1)
    _, first = np.unique(flat, return_index=True)
    is_first = np.zeros(flat.size, dtype=bool)
    is_first[first] = True
    return np.all(is_first.reshape(-1, depth), axis=1, keepdims=False).reshape(-1)


Counts = CountTable | CountSketch


def count_bonus(counts: np.ndarray, beta: float) -> np.ndarray:
    """beta / sqrt(n). A sampled transition has always been counted, so n >= 1 is required."""
    counts = np.asarray(counts)
    if counts.size and counts.min() < 1:
        raise ValueError("bonus asked for a key that was never counted (n = 0)")
    return (beta / np.sqrt(counts)).astype(np.float32)
