"""Timing and statistics every benchmark uses: rotating rounds, medians, ratios, formatting.

The machine is 2 cores shared with other work, so its speed drifts while a benchmark
runs. Every benchmark therefore measures its variants in rounds, in an order that
rotates from round to round (A-B, B-A, ...), so that drift and load hit all variants
alike; it reports medians over rounds and takes ratios within a round. Only the
standard library: importing this loads no BLAS, so it can come before a script sets
its thread variables.
"""

from __future__ import annotations

import io
import platform
import pstats
import statistics
import time
from collections.abc import Callable, Hashable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")
K = TypeVar("K", bound=Hashable)


def median(xs: Iterable[float | None]) -> float | None:
    """The median of the values that exist: a round that measured nothing (None) does
    not count, and no values at all give None rather than an error."""
    got = [x for x in xs if x is not None]
    return statistics.median(got) if got else None


def ratio_median(a: Sequence[float], b: Sequence[float]) -> float:
    """Median over rounds of a[i] / b[i]: each ratio is within one round, so the
    machine's drift between rounds cancels."""
    return statistics.median(x / y for x, y in zip(a, b, strict=True))


def fmt(x: float | None, spec: str = ".1f") -> str:
    """A table cell: `-` where nothing was measured."""
    return "-" if x is None else format(x, spec)


def rotated(items: Sequence[T], r: int) -> list[T]:
    """Round r's order: the items rotated by r, so no item is always first or last."""
    k = r % len(items) if items else 0
    return list(items[k:]) + list(items[:k])


def rotating_rounds(rounds: int, cases: Sequence[T]) -> Iterator[tuple[int, T]]:
    """(round, case) for every case of every round, each round in its rotated order."""
    for r in range(rounds):
        for case in rotated(cases, r):
            yield r, case


def time_per_call(fn: Callable[[], object], calls: int) -> float:
    """Seconds per call of fn over `calls` back-to-back calls."""
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - start) / calls


def measure(
    fns: dict[K, Callable[[], object]], repeats: int, budget_s: float
) -> dict[K, list[float]]:
    """Seconds per call of each fn, one sample per round; rounds interleave the fns (in a
    rotating order) so load from other processes hits them alike."""
    calls = {}
    for name, fn in fns.items():  # warm up and size each run to about budget_s
        for _ in range(3):
            fn()
        calls[name] = max(3, int(budget_s / max(time_per_call(fn, 3), 1e-6)))
    samples: dict[K, list[float]] = {name: [] for name in fns}
    for r in range(repeats):
        for name in rotated(list(fns), r):
            samples[name].append(time_per_call(fns[name], calls[name]))
    return samples


def top_tottime(prof: Path, top: int) -> str:
    """pstats' table of the `top` functions by own time in a cProfile output file."""
    buf = io.StringIO()
    pstats.Stats(str(prof), stream=buf).sort_stats("tottime").print_stats(top)
    return buf.getvalue()


def cpu_model() -> str:
    """The CPU's model name as `lscpu` shows it (every result names the CPU it ran on)."""
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"
