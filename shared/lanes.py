"""Run one function on several blocks of a minibatch at once, in plain threads.

Why threads and not torch's own intra-op threads: on the project's 2-core machines,
shared with actors, the counter and other users, an OpenMP team that spins at every
barrier falls apart as soon as another process takes a core (bench_learner measured
a 2-thread update 5-10x slower than a 1-thread one under load). Here each lane is an
ordinary thread running whole torch operations with one intra-op thread
(`torch.set_num_threads(1)`); torch releases the GIL inside every operation, so two
lanes use two cores when they are free, and when they are not, the lanes are merely
time-sliced: the only waiting is one blocking join per `map`, never a spin.

The caller's thread runs the first block itself; `n - 1` worker threads run the rest.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


class Lanes:
    """`n` lanes: `map(fn, items)` runs fn on every item, up to n at a time."""

    def __init__(self, n: int = 1) -> None:
        if n < 1:
            raise ValueError(f"lanes must be >= 1, got {n}")
        self.n = n
        self._pool = ThreadPoolExecutor(n - 1, thread_name_prefix="lane") if n > 1 else None

    def blocks(self, rows: int) -> list[slice]:
        """`rows` split into min(n, rows) contiguous blocks of near-equal size."""
        k = max(1, min(self.n, rows))
        bounds = [rows * j // k for j in range(k + 1)]
        return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]

    def map(self, fn: Callable[[T], R], items: Sequence[T]) -> list[R]:
        """[fn(item) for item in items], the first here, the others in the workers."""
        if self._pool is None or len(items) < 2:
            return [fn(item) for item in items]
        futures = [self._pool.submit(fn, item) for item in items[1:]]
        first = fn(items[0])
        return [first, *(f.result() for f in futures)]

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __del__(self) -> None:  # workers are daemon-like, but end them when we go
        pool = getattr(self, "_pool", None)
        if pool is not None:
            pool.shutdown(wait=False)
