"""Run one function on several blocks of a minibatch at once, in plain threads; and
pick, from measured times, how many threads an update should use.

Lanes are an alternative to torch's own intra-op threads: on the project's 2-core
machines, shared with actors, the counter and other users, an OpenMP team that spins at
every barrier falls apart as soon as another process takes a core (slower than one
thread, often by far: bench_learner.py's "one core busy" line). Each lane is an ordinary
thread running whole torch operations with one intra-op thread; torch releases the GIL
inside every operation, so two lanes use two cores when they are free, and when they are
not they are time-sliced with one blocking join per `map`, never a spin. They still take
the GIL back between operations, which makes them slower than torch's threads on an idle
machine; `LaneTuner` therefore measures which of one thread, two lanes and two torch
threads is fastest now and keeps measuring.

The caller's thread runs the first block itself; `n - 1` worker threads run the rest.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence
from concurrent.futures import ThreadPoolExecutor
from statistics import median
from typing import Generic, TypeVar

T = TypeVar("T")
R = TypeVar("R")
O = TypeVar("O", bound=Hashable)  # noqa: E741 (an option: lanes, or (lanes, threads))


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


class LaneTuner(Generic[O]):
    """Picks the fastest of several ways to run the update (lane counts, torch thread
    counts) from measured update times, and keeps checking, because the machine's load
    changes under it.

    Why: on an idle 2-core machine two threads (lanes, or torch's own) are faster than
    one; when other processes keep the cores busy they are slower, torch's spinning
    OpenMP threads by far (bench_learner.py's "one core busy" line; docs/performance.md,
    "Learner design and its measurements"). No fixed choice is right on a shared
    machine, and the update's result differs between them only in the order of
    floating-point additions.

    Updates run in blocks of `block` with one choice; a block's median update time
    updates that choice's moving average (a probe's block replaces it). Each choice
    is tried once first; after that the fastest runs, and the others are probed with
    one block each, every `probe_every` blocks. A probe that is losing is cut short:
    at once by an update slower than `ruin_factor` times the best choice's estimate,
    otherwise once the median of at least `min_probe` of its updates is slower than
    `abort_factor` times it. A choice that loses a probe waits twice as long for the
    next (up to `max_backoff` times), one that wins is probed at the normal rate
    again, so a choice that is ruinous under the current load costs a single update
    now and then, while a change in load is still noticed.

    Medians, not means: other processes stall an update now and then whatever the
    choice (an evaluator's burst preempts a thread mid-update), and one such stall must
    not decide a probe; a choice that is slower under the load shows it in most of its
    updates, which the median sees (tests/test_lanes.py reproduces such stalls).
    """

    def __init__(
        self,
        options: Sequence[O],
        block: int = 20,
        probe_every: int = 10,
        smoothing: float = 0.5,
        abort_factor: float = 2.0,
        max_backoff: int = 32,
        ruin_factor: float = 8.0,
        min_probe: int = 3,
    ) -> None:
        if not options:
            raise ValueError("LaneTuner needs at least one option")
        self.options = list(options)
        self.block, self.probe_every, self.smoothing = block, probe_every, smoothing
        self.abort_factor, self.max_backoff = abort_factor, max_backoff
        self.ruin_factor, self.min_probe = ruin_factor, min_probe
        self.estimate_s: dict[O, float | None] = dict.fromkeys(self.options)  # smoothed medians
        self.backoff: dict[O, int] = dict.fromkeys(self.options, 1)
        self._wait: dict[O, int] = dict.fromkeys(self.options, 0)  # blocks since probed
        self.current = self.options[0]
        self.chosen = dict.fromkeys(self.options, 0)  # updates run with each option
        self.aborted = 0  # probes cut short
        self._times: list[float] = []  # this block's update times

    def choose(self) -> O:
        return self.current

    def record(self, seconds: float) -> None:
        """The time of one update run with `choose()`'s answer."""
        self.chosen[self.current] += 1
        self._times.append(seconds)
        best = self.best()
        best_s = self.estimate_s[best]
        if self.current != best and best_s is not None:
            ruinous = seconds > self.ruin_factor * best_s
            losing = (
                len(self._times) >= self.min_probe
                and median(self._times) > self.abort_factor * best_s
            )
            if ruinous or losing:
                self.aborted += 1
                self._end_block()
                return
        if len(self._times) >= self.block:
            self._end_block()

    def best(self) -> O:
        known = {k: v for k, v in self.estimate_s.items() if v is not None}
        return min(known, key=known.__getitem__) if known else self.options[0]

    def _end_block(self) -> None:
        done, typical = self.current, median(self._times)
        old = self.estimate_s[done]
        # Smoothed over consecutive blocks; a probe's estimate is its own block's alone
        # (the last one is many blocks old, from another load).
        consecutive = old is not None and self._wait[done] == 0
        self.estimate_s[done] = (
            self.smoothing * typical + (1 - self.smoothing) * old
            if old is not None and consecutive
            else typical
        )
        self._times = []
        best = self.best()
        if done != best and old is not None:  # a probe that lost: probe it less often
            self.backoff[done] = min(self.max_backoff, 2 * self.backoff[done])
        elif done == best:
            self.backoff[done] = 1
        self._wait[done] = 0
        for k in self.options:
            if k != done:
                self._wait[k] += 1
        self.current = self._next(best)

    def _next(self, best: O) -> O:
        untried = [k for k, v in self.estimate_s.items() if v is None]
        if untried:
            return untried[0]
        due = [
            k
            for k in self.options
            if k != best and self._wait[k] >= self.probe_every * self.backoff[k]
        ]
        return max(due, key=self._wait.__getitem__) if due else best
