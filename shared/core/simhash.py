"""SimHash codes phi(v) = sgn(A v) packed into compact table keys.

The thesis hashes continuous state-action vectors so that near vectors share a
count. A code is ternary ({-1, 0, 1}^k); 0 only occurs when a projection is exactly
zero (e.g. an all-zero vector), but it must not be confused with -1, so a key packs
two bit planes: "positive" and "zero". For k bits a key is 2 * ceil(k / 8) bytes.

Keys are returned as a contiguous uint8 matrix (one row per vector) and, for table
look-ups, as fixed-width numpy void scalars / bytes so that a whole batch is hashed
with one matrix product and one packbits call.
"""

from __future__ import annotations

import numpy as np


class SimHash:
    """A seeded k x D Gaussian projection; `keys(batch)` hashes a whole batch at once."""

    def __init__(self, dim: int, k: int, seed: int) -> None:
        if dim < 1:
            raise ValueError(f"dim must be >= 1, got {dim}")
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        self.dim = dim
        self.k = k
        self.seed = seed
        # float64 so that the sign of a projection does not depend on BLAS blocking.
        self.A = np.random.default_rng(seed).standard_normal((k, dim))
        self.key_bytes = 2 * ((k + 7) // 8)

    def codes(self, batch: np.ndarray) -> np.ndarray:
        """sgn(A v) for each row: int8 matrix (B, k) with values in {-1, 0, 1}."""
        proj = self._project(batch)
        return np.sign(proj).astype(np.int8)

    def keys(self, batch: np.ndarray) -> np.ndarray:
        """Packed keys, uint8 matrix (B, key_bytes): positive-plane bits then zero-plane bits."""
        proj = self._project(batch)
        pos = np.packbits(proj > 0, axis=1)
        zero = np.packbits(proj == 0, axis=1)
        return np.ascontiguousarray(np.concatenate([pos, zero], axis=1))

    def _project(self, batch: np.ndarray) -> np.ndarray:
        v = np.asarray(batch, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != self.dim:
            raise ValueError(f"expected a (B, {self.dim}) batch, got shape {v.shape}")
        return v @ self.A.T


class RoundKey:
    """The thesis's "without hash" variant: the key is the vector rounded to `decimals`
    (the thesis: 2)."""

    def __init__(self, dim: int, decimals: int = 2) -> None:
        self.dim = dim
        self.decimals = decimals
        # int32 holds |v| < 214,748 at 4 decimals; more decimals take int64 (the 2 of the
        # thesis keep their 4-byte keys).
        self.dtype = np.int32 if decimals <= 4 else np.int64
        self.key_bytes = np.dtype(self.dtype).itemsize * dim

    def keys(self, batch: np.ndarray) -> np.ndarray:
        v = np.asarray(batch, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != self.dim:
            raise ValueError(f"expected a (B, {self.dim}) batch, got shape {v.shape}")
        # Integer hundredths: exact, and -0.0 and 0.0 become the same key.
        scaled = np.rint(v * 10**self.decimals).astype(self.dtype)
        return np.ascontiguousarray(scaled.view(np.uint8).reshape(len(v), -1))


class RawKey:
    """The thesis code's strategy 'None' (its fig. 3 loop at commit 92fc6f5,
    `count_based.py:33`): the key is the vector's raw float32 bytes, no hash, no rounding
    (-0.0 and 0.0 made one key). Continuous observations then almost never repeat, so
    priced at collection every key has n = 1: a constant bonus beta."""

    def __init__(self, dim: int) -> None:
        self.dim = dim
        self.key_bytes = 4 * dim

    def keys(self, batch: np.ndarray) -> np.ndarray:
        v = np.asarray(batch, dtype=np.float32)
        if v.ndim != 2 or v.shape[1] != self.dim:
            raise ValueError(f"expected a (B, {self.dim}) batch, got shape {v.shape}")
        v = v + np.float32(0.0)  # -0.0 -> 0.0
        return np.ascontiguousarray(v.view(np.uint8).reshape(len(v), -1))


def as_void(keys: np.ndarray) -> np.ndarray:
    """View a (B, W) uint8 key matrix as B fixed-width void scalars (hashable, sortable)."""
    keys = np.ascontiguousarray(keys, dtype=np.uint8)
    return keys.view(np.dtype((np.void, keys.shape[1]))).reshape(-1)
