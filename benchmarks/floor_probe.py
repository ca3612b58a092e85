"""The machine's speed for the learner's workload now: bench_learner's floor, 1 and 2 threads.

bench_e2e runs this in a child just before and after each run. The host is shared with
other guests and what it gives the second thread varies most (the two-thread floor ran
1.4x-2.05x the one-thread floor on different days), so a run's steps/s mean more next
to the update's matrix products alone (bench_learner's floor, speaker_listener,
Cen-MADDPG) timed around it. A child, so the benchmark's own process loads no torch
and the probe gets the thread settings its parent gives it.

    .venv/bin/python benchmarks/floor_probe.py [SECONDS]

prints {"1": updates/s on one thread, "2": updates/s on two} (medians) as JSON.
"""

from __future__ import annotations

import json
import statistics
import sys
import time

import bench_learner as bl
import torch
from _stats import time_per_call


def floor_rates(seconds: float) -> dict[int, float]:
    """Median floor updates/s on 1 and 2 torch threads, `seconds` of samples each."""
    floor = bl.floor_ops(bl.batched(bl.SPEAKER_LISTENER))
    out = {}
    for threads in (1, 2):
        torch.set_num_threads(threads)
        for _ in range(10):
            floor()
        rates, end = [], time.perf_counter() + seconds
        while time.perf_counter() < end:
            rates.append(1 / time_per_call(floor, 5))
        out[threads] = statistics.median(rates)
    return out


if __name__ == "__main__":
    print(json.dumps(floor_rates(float(sys.argv[1]) if len(sys.argv) > 1 else 0.7)))
