"""Subnormal Adam moments: what a trained learner's update costs with and without flushing.

Trains the thesis's speaker_listener arm (Cen-MADDPG + Cen-MACB k 512 beta 0.8, batch 100,
400-300) with `macb train` for `--episodes` (default 300) with `flush_denormals: false`,
so its Adam moments are what IEEE arithmetic leaves them; counts the subnormal share of
each; then loads the checkpoint into two batched learners per precision, one with
`flush_denormals` off and one on (the default), and times their updates on one random
minibatch in rotating rounds, on one and on two torch threads. Ratios are medians of
per-round ratios. `--checkpoint` reuses a checkpoint.pt instead of training.

    .venv/bin/python benchmarks/bench_denormals.py [--episodes 300] [--rounds 9]

prints markdown tables and writes benchmarks/results/denormals.json.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import tempfile
from pathlib import Path

import torch
from _harness import (
    THESIS_ARM,
    add_out,
    bench_parser,
    command,
    macb_argv,
    progress,
    write_result,
)
from _stats import measure, ratio_median
from bench_learner import SPEAKER_LISTENER, random_batch

from shared.core.learners import BatchedMADDPG, LearnerSpec

TINY = torch.finfo(torch.float32).tiny


def train(episodes: int, work: Path) -> Path:
    cfg = work / "arm.yaml"
    lines = [f"{k}: {v}" for k, v in THESIS_ARM.items()]
    lines += [f"episodes: {episodes}", "seed: 0", "flush_denormals: false"]
    cfg.write_text("\n".join(lines) + "\n")
    out = work / "run"
    progress(f"training {episodes} episodes with flush_denormals false ...")
    subprocess.run(
        macb_argv("train", "--config", str(cfg), "--out", str(out), "--quiet"),
        check=True,
        capture_output=True,
    )
    return out / "checkpoint.pt"


def subnormal_shares(state: dict) -> dict[str, float]:
    """Per kind of tensor in a learner state, the share of its values that are subnormal."""
    shares: dict[str, list[int]] = {}

    def add(kind: str, t: torch.Tensor) -> None:
        n, s = shares.setdefault(kind, [0, 0])
        sub = int(((t != 0) & (t.abs() < TINY)).sum())
        shares[kind] = [n + t.numel(), s + sub]

    for net in ("actors", "critics"):
        for sd in state[net]:
            for t in sd.values():
                add(f"{net} weights", t)
        for opt in state[f"{net[:-1]}_optims"]:
            for st in opt["state"].values():
                add(f"{net[:-1]} exp_avg", st["exp_avg"])
                add(f"{net[:-1]} exp_avg_sq", st["exp_avg_sq"])
    return {k: s / n for k, (n, s) in shares.items()}


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__, "denormals.json")
    parser.add_argument("--episodes", type=int, default=300, help="training episodes (300)")
    parser.add_argument("--rounds", type=int, default=9, help="rotating rounds (default 9)")
    parser.add_argument("--checkpoint", type=Path, help="a checkpoint.pt to use instead")
    add_out(parser, "denormals.json")
    args = parser.parse_args(argv)
    load = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="macb-denormals-") as tmp:
        path = args.checkpoint or train(args.episodes, Path(tmp))
        state = torch.load(path, weights_only=True)["learner"]
    shares = subnormal_shares(state)
    print("\n| tensors | subnormal share |\n|---|---|")
    for kind, share in shares.items():
        print(f"| {kind} | {share:.1%} |")
    rows = []
    for threads in (1, 2):
        for precision in ("fp32", "bf16"):
            torch.set_num_threads(1)
            fns = {}
            for flush in (False, True):
                spec = LearnerSpec(algo="cen-maddpg", flush_denormals=flush)
                m = BatchedMADDPG(SPEAKER_LISTENER, spec, precision=precision)
                m.load_state_dict(state)
                b = random_batch(m)
                fns[flush] = lambda m=m, b=b: m.update(*b)
            torch.set_num_threads(threads)
            progress(f"{precision}, {threads} thread(s) ...")
            samples = measure(fns, args.rounds, 0.3)
            rows.append(
                {
                    "precision": precision,
                    "threads": threads,
                    "kept_ms": 1e3 * statistics.median(samples[False]),
                    "flushed_ms": 1e3 * statistics.median(samples[True]),
                    "speedup": ratio_median(samples[False], samples[True]),
                    "samples_s": {str(k): v for k, v in samples.items()},
                }
            )
    torch.set_num_threads(1)
    print("\n| precision | torch threads | subnormals kept: ms per update | flushed | speed, "
          "flushed / kept |\n|---|---|---|---|---|")  # fmt: skip
    for r in rows:
        print(f"| {r['precision']} | {r['threads']} | {r['kept_ms']:.2f} | {r['flushed_ms']:.2f} "
              f"| {r['speedup']:.2f}x |")  # fmt: skip
    write_result(
        args.out,
        {
            "command": command(__file__, argv),
            "episodes": args.episodes,
            "subnormal_shares": shares,
            "rows": rows,
        },
        load,
    )


if __name__ == "__main__":
    main()
