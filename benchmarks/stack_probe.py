"""Would several runs in one stacked update pay? A probe for issue 13's optional item.

Stacked runs (seeds or arms of one task and network shape as further entries of the
learner's stacks) were not built when this was written; they are now run groups
(shared/core/learners/group.py; benchmarks/bench_group.py measures them). This measures what
they could buy with the batched learner alone:
a BatchedMADDPG of R x speaker_listener's two agents under Dis-MADDPG (every network
reads its own agent's columns, so R runs' networks are R independent copies of one
run's, the same shapes a stacked learner would have; Cen critics would each read their
own run's joint input, a copy more per update), against one run's two agents. Per-run
update time = stacked time / R; rotating rounds, per-round ratios, one torch thread.

`--two-cores` asks the question for the 2-core machine instead, in total run-updates/s
over a few seconds of each case, in rotating rounds: two runs as two processes (each
one run's learner on one torch thread, as `macb up --slots 2` runs them), one process
whose learner stacks both runs on two torch threads, and two processes stacking
`--runs` runs each on one thread (2 x runs runs at once).

    .venv/bin/python benchmarks/stack_probe.py [--runs 3] [--rounds 9] [--two-cores]
        [--seconds 3]

prints a markdown table.
"""

from __future__ import annotations

import argparse
import multiprocessing
import statistics
import time

import torch
from _stats import measure, ratio_median, rotating_rounds
from bench_learner import SPEAKER_LISTENER, BatchedMADDPG, batched, learner_pair

from shared.core.learners.precision import native_bf16


def precisions() -> tuple[str, ...]:
    """The precisions this CPU runs: bf16 only with native bf16 (elsewhere a bf16
    learner runs fp32, and its row would be fp32's under bf16's name)."""
    if native_bf16():
        return ("fp32", "bf16")
    print("bf16: skipped, this CPU has no native bf16 (the learner would run fp32)")
    return ("fp32",)


def stacked(runs: int, precision: str) -> tuple[BatchedMADDPG, tuple]:
    """A learner whose stacks hold `runs` runs of speaker_listener's agents (Dis-MADDPG),
    with the reference's initial weights, and a random minibatch for it."""
    agents = SPEAKER_LISTENER * runs
    _, fast, b = learner_pair(agents, "dis-maddpg")
    m = batched(agents, "dis-maddpg", precision=precision)
    m.load_state_dict(fast.state_dict())
    return m, b


def _updates_for(runs: int, precision: str, threads: int, seconds: float, start, out) -> None:
    """In a process of its own: a learner stacking `runs` runs, updated for `seconds`
    from `start` (a barrier), its run-updates/s put on `out`."""
    torch.set_num_threads(threads)
    m, b = stacked(runs, precision)
    for _ in range(20):
        m.update(*b)
    start.wait()
    done, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        m.update(*b)
        done += 1
    out.put(runs * done / (time.perf_counter() - t0))


def two_cores(runs: int, rounds: int, seconds: float = 3.0) -> None:
    """Runs on the two cores: as processes, or stacked in one on two threads, or stacked
    in each of two processes on one thread each."""
    ctx = multiprocessing.get_context("spawn")
    cases = {  # (runs stacked, torch threads) per process
        "procs": [(1, 1), (1, 1)],
        "stacked": [(2, 2)],
        "per_core": [(runs, 1), (runs, 1)],
    }
    which = precisions()  # says so first when bf16 is skipped
    print(f"\n| precision | 2 processes x 1 run: run-updates/s | 1 process, 2 stacked, 2 "
          f"threads | stacked / processes | 2 processes x {runs} stacked, 1 thread each "
          "| per-core stacked / processes |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for precision in which:
        totals: dict[str, list[float]] = {case: [] for case in cases}
        for _, case in rotating_rounds(rounds, list(cases)):
            jobs = cases[case]
            start, out = ctx.Barrier(len(jobs)), ctx.Queue()
            procs = [
                ctx.Process(target=_updates_for, args=(n, precision, t, seconds, start, out))
                for n, t in jobs
            ]
            for p in procs:
                p.start()
            rates = [out.get(timeout=300) for _ in procs]
            for p in procs:
                p.join()
            totals[case].append(sum(rates))
        med = {case: statistics.median(totals[case]) for case in cases}
        stacked = ratio_median(totals["stacked"], totals["procs"])
        per_core = ratio_median(totals["per_core"], totals["procs"])
        print(
            f"| {precision} | {med['procs']:.1f} | {med['stacked']:.1f} | {stacked:.2f}x "
            f"| {med['per_core']:.1f} | {per_core:.2f}x |"
        )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3, help="runs stacked (default 3)")
    parser.add_argument("--rounds", type=int, default=9, help="rotating rounds (default 9)")
    parser.add_argument(
        "--seconds", type=float, default=3.0,
        help="--two-cores: seconds of updates per case (default 3)",
    )  # fmt: skip
    parser.add_argument(
        "--two-cores", action="store_true",
        help="two runs as two processes against two stacked in one on two threads",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if args.two_cores:
        two_cores(args.runs, args.rounds, args.seconds)
        return
    torch.set_num_threads(1)
    rows = []
    for precision in precisions():
        fns = {}
        for r in (1, args.runs):
            m, b = stacked(r, precision)
            fns[r] = lambda m=m, b=b: m.update(*b)
        samples = measure(fns, args.rounds, 0.3)
        per_run = {r: [t / r for t in samples[r]] for r in samples}
        speedup = ratio_median(per_run[1], per_run[args.runs])
        one = 1e3 * statistics.median(per_run[1])
        many = 1e3 * statistics.median(per_run[args.runs])
        rows.append((precision, one, many, speedup))
    print(f"\n| precision | 1 run: ms per update | {args.runs} stacked: ms per run-update "
          "| per-run speed, stacked / alone |")  # fmt: skip
    print("|---|---|---|---|")
    for precision, one, many, speedup in rows:
        print(f"| {precision} | {one:.2f} | {many:.2f} | {speedup:.2f}x |")


if __name__ == "__main__":
    main()
