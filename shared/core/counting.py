"""Count tables for SimHash (or rounded) keys, and the bonus beta / sqrt(n).

A table is only ever incremented with freshly *collected* training transitions;
look-ups (`counts`) never change it, so sampling a batch any number of times or
running evaluation episodes leaves the counts alone (thesis section 4.5.2: counting
at sample time makes the bonus vanish).
"""

from __future__ import annotations

from itertools import islice

import numpy as np


class CountTable:
    """A dictionary from packed keys (bytes) to visit counts, with cheap summary stats."""

    def __init__(self, key_bytes: int) -> None:
        self.key_bytes = key_bytes
        self._counts: dict[bytes, int] = {}
        self.total = 0  # transitions counted
        self.count1 = 0  # keys seen exactly once

    def __len__(self) -> int:
        return len(self._counts)

    def _split(self, keys: np.ndarray) -> list[bytes]:
        keys = np.ascontiguousarray(keys, dtype=np.uint8)
        if keys.ndim != 2 or keys.shape[1] != self.key_bytes:
            raise ValueError(f"expected (B, {self.key_bytes}) uint8 keys, got {keys.shape}")
        w = self.key_bytes
        raw = keys.tobytes()
        return [raw[i : i + w] for i in range(0, len(raw), w)]

    def increment(self, keys: np.ndarray) -> None:
        """Count each row once (a batch of collected transitions)."""
        table = self._counts
        for key in self._split(keys):
            n = table.get(key, 0) + 1
            table[key] = n
            if n == 1:
                self.count1 += 1
            elif n == 2:
                self.count1 -= 1
        self.total += len(keys)

    def counts(self, keys: np.ndarray) -> np.ndarray:
        """n(key) for each row, 0 for unseen keys; never modifies the table."""
        get = self._counts.get
        return np.fromiter((get(k, 0) for k in self._split(keys)), dtype=np.int64, count=len(keys))

    @property
    def count1_pct(self) -> float:
        """Share of keys seen exactly once, in percent (the thesis's count-1 percentage)."""
        return 100.0 * self.count1 / len(self._counts) if self._counts else 0.0

    def memory_bytes(self) -> int:
        """Approximate resident size: dict slots plus the key and int objects."""
        import sys

        n = len(self._counts)
        if n == 0:
            return sys.getsizeof(self._counts)
        some_key = next(iter(self._counts))
        return sys.getsizeof(self._counts) + n * (sys.getsizeof(some_key) + 28)

    def to_arrays(self, chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:
        """(keys (n, key_bytes) uint8, counts (n,) int64) for a pickle-free snapshot.

        Built `chunk` keys at a time: in one piece the join and the fromiter are C
        calls that hold the GIL for the whole table (~0.17 s for a million 128-byte
        keys), stalling every other thread of the process (the counter answers bonus
        queries on another thread while it snapshots). The table must not change
        meanwhile (its one writer is the caller's thread).
        """
        n, w = len(self._counts), self.key_bytes
        keys = np.empty((n, w), dtype=np.uint8)
        counts = np.empty(n, dtype=np.int64)
        flat = keys.reshape(-1)
        key_it, count_it = iter(self._counts), iter(self._counts.values())
        for start in range(0, n, chunk):
            m = min(chunk, n - start)
            raw = b"".join(islice(key_it, m))
            flat[start * w : (start + m) * w] = np.frombuffer(raw, dtype=np.uint8)
            counts[start : start + m] = np.fromiter(islice(count_it, m), np.int64, count=m)
        return keys, counts

    @classmethod
    def from_arrays(cls, keys: np.ndarray, counts: np.ndarray, total: int) -> CountTable:
        table = cls(int(keys.shape[1]) if keys.ndim == 2 else 0)
        w = table.key_bytes
        raw = np.ascontiguousarray(keys, dtype=np.uint8).tobytes()
        table._counts = {raw[i * w : (i + 1) * w]: int(c) for i, c in enumerate(counts)}
        table.count1 = int(np.sum(counts == 1))
        table.total = int(total)
        return table


def count_bonus(counts: np.ndarray, beta: float) -> np.ndarray:
    """beta / sqrt(n). A sampled transition has always been counted, so n >= 1 is required."""
    counts = np.asarray(counts)
    if counts.size and counts.min() < 1:
        raise ValueError("bonus asked for a key that was never counted (n = 0)")
    return (beta / np.sqrt(counts)).astype(np.float32)
