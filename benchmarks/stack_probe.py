"""Would several runs in one stacked update pay? A probe for issue 13's optional item.

Stacked runs (seeds or arms of one task and network shape as further entries of the
learner's stacks) are not built. This measures what they could buy, with what exists:
a BatchedMADDPG of R x speaker_listener's two agents under Dis-MADDPG (every network
reads its own agent's columns, so R runs' networks are R independent copies of one
run's, the same shapes a stacked learner would have; Cen critics would each read their
own run's joint input, a copy more per update), against one run's two agents. Per-run
update time = stacked time / R; rotating rounds, per-round ratios, one torch thread.

    .venv/bin/python benchmarks/stack_probe.py [--runs 3] [--rounds 9]

prints a markdown table.
"""

from __future__ import annotations

import argparse
import statistics

import torch
from _stats import measure, ratio_median
from bench_learner import SPEAKER_LISTENER, batched, learner_pair


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3, help="runs stacked (default 3)")
    parser.add_argument("--rounds", type=int, default=9, help="rotating rounds (default 9)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    for precision in ("fp32", "bf16"):
        fns = {}
        for r in (1, args.runs):
            agents = SPEAKER_LISTENER * r
            _, fast, b = learner_pair(agents, "dis-maddpg")
            m = batched(agents, "dis-maddpg", precision=precision)
            m.load_state_dict(fast.state_dict())
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
