"""Does torch's CPU bf16 path use native bf16 instructions here? Flags, kernels, speed.

`precision: bf16` pays only where the matrix products run on bf16 dot-product
instructions; this checks a machine before trusting the learner's bf16 numbers:

* the CPU flags the detection reads (shared.core.learners.precision: avx512_bf16, amx_bf16);
* which oneDNN kernel runs each of the learner's bf16 product shapes (a child process
  with ONEDNN_VERBOSE=1; `avx512_core_bf16` or `amx` in the name is native);
* per shape, fp32 against bf16 time of the same product through layers.py's
  `linear_*` (rotating rounds, per-round ratios), and GFLOP/s of the largest.

    .venv/bin/python benchmarks/bf16_probe.py [--rounds R]

prints markdown tables (one torch thread).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import torch
from _stats import measure, ratio_median

from shared.core.learners.layers import linear_forward, linear_grad_input, linear_grad_weight
from shared.core.learners.precision import NATIVE_BF16_FLAGS, cpu_flags, native_bf16

# (name, N agents, rows, fan_in, fan_out): speaker_listener's layers at hidden 400-300.
SHAPES = [
    ("critic in 19 -> 400", 2, 100, 19, 400),
    ("actor in 11 -> 400", 2, 100, 11, 400),
    ("hidden 400 -> 300", 2, 100, 400, 300),
    ("critic out 300 -> 1", 2, 100, 300, 1),
    ("actor out 300 -> 3", 2, 100, 300, 3),
]


def products(dtype: torch.dtype, n: int, rows: int, fan_in: int, fan_out: int) -> dict:
    """The layer's three products (forward, input and weight gradients) in `dtype`."""
    x, w = torch.randn(n, rows, fan_in, dtype=dtype), torch.randn(n, fan_out, fan_in, dtype=dtype)
    b, g = torch.randn(n, 1, fan_out, dtype=dtype), torch.randn(n, rows, fan_out, dtype=dtype)
    return {
        "forward": lambda: linear_forward(x, w, b),
        "grad_input": lambda: linear_grad_input(g, w),
        "grad_weight": lambda: linear_grad_weight(g, x),
    }


def kernels() -> list[str]:
    """oneDNN's verbose lines for one bf16 run of every product (from a child)."""
    code = (
        "import sys; sys.path[:0] = [sys.argv[1]]; import torch; import bf16_probe as p\n"
        "torch.set_num_threads(1)\n"
        "for _, *shape in p.SHAPES:\n"
        "    for f in p.products(torch.bfloat16, *shape).values(): f()\n"
    )
    here = os.path.dirname(os.path.abspath(__file__))
    env = {**os.environ, "ONEDNN_VERBOSE": "1"}
    out = subprocess.run(
        [sys.executable, "-c", code, here], env=env, capture_output=True, text=True, check=True
    ).stdout
    return [line for line in out.splitlines() if ",exec," in line]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=9, help="rounds (default 9)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        flags = cpu_flags(Path("/proc/cpuinfo").read_text())
    except OSError:
        flags = set()
    found = [f for f in NATIVE_BF16_FLAGS if f in flags]
    print(f"CPU bf16 flags: {found or 'none'}; native_bf16() = {native_bf16()}")
    print(f"torch {torch.__version__}, load average {os.getloadavg()}\n")
    names = sorted({line.split(",")[6] for line in kernels()})  # the implementation
    print("oneDNN kernels of the bf16 products: " + ", ".join(names) + "\n")

    fns: dict[str, Callable[[], object]] = {}
    for name, *shape in SHAPES:
        for dtype, tag in ((torch.float32, "fp32"), (torch.bfloat16, "bf16")):
            for what, fn in products(dtype, *shape).items():
                fns[f"{name}|{what}|{tag}"] = fn
    samples = measure(fns, args.rounds, 0.03)
    print("| layer | product | fp32 us | bf16 us | fp32 / bf16 time |")
    print("|---|---|---|---|---|")
    for name, *_ in SHAPES:
        for what in ("forward", "grad_input", "grad_weight"):
            a, b = samples[f"{name}|{what}|fp32"], samples[f"{name}|{what}|bf16"]
            print(
                f"| {name} | {what} | {1e6 * statistics.median(a):.1f} "
                f"| {1e6 * statistics.median(b):.1f} | {ratio_median(a, b):.2f}x |"
            )
    name, n, rows, fan_in, fan_out = SHAPES[2]
    flop = 2 * n * rows * fan_in * fan_out
    rate = {
        tag: flop / statistics.median(samples[f"{name}|forward|{tag}"]) / 1e9
        for tag in ("fp32", "bf16")
    }
    print(
        f"\n{name} forward ({n} x {rows}x{fan_in} by {fan_in}x{fan_out}): "
        f"fp32 {rate['fp32']:.0f} GFLOP/s, bf16 {rate['bf16']:.0f} GFLOP/s"
    )
    print(f"\nload average after {os.getloadavg()}")


if __name__ == "__main__":
    main()
