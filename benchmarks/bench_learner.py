"""Learner update speed: reference MADDPG vs BatchedMADDPG vs the matrix-product floor.

For each task the same random minibatch (batch 100, hidden 400-300, the thesis settings)
is fed to

* `ref`: shared.core.learners.MADDPG, the per-agent reference update;
* `batched`: shared.core.learners.BatchedMADDPG, a copy of the same learner;
* `floor`: only the matrix products one batched update performs (forward and backward
  of every stacked layer, with the same shapes and layouts, through the same
  `linear_*` functions), on preallocated tensors: no elementwise ops, no autograd, no
  optimizer, no target update. It is what an update would cost if everything but the
  matrix products were free.
* `lanes2`: BatchedMADDPG with `lanes=2` (what the platform runs by default): the rows
  split over two threads; `floor_lanes2`: the floor's products for half the rows, in
  the same two threads, its floor on two cores.

A last measurement runs speaker_listener while another process spins on one core: one
lane, two lanes, torch's own two intra-op threads, and `TunedMADDPG` (the default,
`learner_lanes: auto`: a tuner picks 1 or 2 by measured speed), to show what each does
when the second core is not free.

A second table (`precision: bf16`) times, per task, the fp32 batched update, the same
update with bf16 matrix products (`bf16`), both floors (`floor_bf16`: the floor's
products in bf16, with oneDNN's bf16 layouts), bf16 without the fused master-weight
kernel (`bf16_unfused`: torch's Adam, lerp and casts; shared/core/learners/fused.py) and bf16
on two lanes, in the same rounds; plus a 2-thread speaker_listener row (where the
learner runs torch's ops, so fused and unfused are the same code). `--precision fp32`
or `bf16` runs one table only.

Measurements run in rounds (about 0.15 s of each of ref, batched, floor, in a rotating
order) so load from other processes on the shared machine hits all three alike. Rates
are medians over rounds; ratios are medians of the ratios within each round. The floor
runs on hot caches and still pays Python's cost of ~30 calls: it is a floor for
arithmetic, not a reachable target. Threads: 1 for the table (the choice for a learner
on 2 cores shared with actors and the counter), plus a 2-thread speaker_listener row.

    .venv/bin/python benchmarks/bench_learner.py [--quick] [--precision fp32|bf16|both]

prints a markdown table and writes benchmarks/results/learner.json.
"""

from __future__ import annotations

import multiprocessing
import os
import platform
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch
from _harness import add_out, bench_parser, command, progress, write_result
from _stats import fmt, measure, ratio_median

# The benchmarks' one import site of the learners (bench_scaling and floor_probe.py use
# them through the helpers below).
from shared.core.learners import MADDPG, AgentDims, BatchedMADDPG, Lanes, LearnerSpec, TunedMADDPG
from shared.core.learners.fused import kernel as fused_kernel
from shared.core.learners.layers import linear_forward, linear_grad_input, linear_grad_weight
from shared.core.learners.precision import native_bf16

BATCH = 100
HIDDEN = (400, 300)
MOVE = ((-1.0, -1.0), (1.0, 1.0))


def spread(n: int) -> list[AgentDims]:
    return [AgentDims(4 + 2 * n + 4 * (n - 1), *MOVE)] * n


SPEAKER_LISTENER = [AgentDims(3, (0.0,) * 3, (1.0,) * 3), AgentDims(11, *MOVE)]
# (task, N, algo, agent dims); the dims are what shared.envs.tasks.task_spec reports for mpe2.
CASES = [
    ("simple", 1, "ddpg", [AgentDims(4, *MOVE)]),
    ("spread", 2, "dis-maddpg", spread(2)),
    ("spread", 2, "cen-maddpg", spread(2)),
    ("speaker_listener", 2, "cen-maddpg", SPEAKER_LISTENER),
    ("spread", 3, "cen-maddpg", spread(3)),
    ("spread", 4, "cen-maddpg", spread(4)),
]


def check_dims() -> None:
    """The hard-coded dims above must be the project's (skipped if mpe2 is missing)."""
    try:
        from shared.envs.tasks import task_spec
    except ImportError:
        return
    for task, n, _, agents in CASES:
        got = [(a.obs_dim, tuple(a.act_low), tuple(a.act_high)) for a in task_spec(task, n).agents]
        want = [(a.obs_dim, a.act_low, a.act_high) for a in agents]
        if got != want:
            raise SystemExit(f"{task} N={n}: dims {want} differ from shared.envs.tasks {got}")


def random_batch(m: MADDPG, seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    o, a = m.obs_off[-1], m.act_off[-1]
    return (
        rng.standard_normal((BATCH, o)).astype(np.float32),
        rng.uniform(-1, 1, (BATCH, a)).astype(np.float32),
        rng.uniform(-1, 0, (BATCH, m.n)).astype(np.float32),
        rng.standard_normal((BATCH, o)).astype(np.float32),
        (rng.uniform(0, 1, BATCH) < 0.05).astype(np.float32),
    )


def floor_ops(m: BatchedMADDPG, rows: int = BATCH) -> Callable[[], None]:
    """The matrix products of one BatchedMADDPG.update (of `rows` rows), preallocated, in
    the dtype the learner's products run in (`m.dtype`: fp32, or bf16 with
    `precision="bf16"`)."""
    n, dt = m.n, m.dtype

    def layers(params: list[torch.Tensor], shared_input: bool) -> list[tuple]:
        out = []
        for k, w in enumerate(params[0::2]):
            w = torch.randn_like(w.detach(), dtype=dt)
            _, fan_out, fan_in = w.shape
            x = (
                torch.randn(rows, fan_in, dtype=dt).expand(n, -1, -1)
                if shared_input and k == 0
                else torch.randn(n, rows, fan_in, dtype=dt)
            )
            b, g = torch.randn(n, 1, fan_out, dtype=dt), torch.randn(n, rows, fan_out, dtype=dt)
            out.append((x, w, b, g))
        return out

    actor = layers(m.actor.params, False)
    critic_shared = layers(m.critic.params, m.centralized)  # targets and critic step
    critic_own = layers(m.critic.params, False)  # actor step: input differs per agent

    def forward(ls):
        for x, w, b, _ in ls:
            linear_forward(x, w, b)

    def backward(ls, weights: bool, first_input: bool):
        for k in reversed(range(len(ls))):
            x, w, _, g = ls[k]
            if weights:
                linear_grad_weight(g, x)
            if k > 0 or first_input:
                linear_grad_input(g, w)

    def one_update() -> None:
        with torch.no_grad():
            forward(actor)  # target actors
            forward(critic_shared)  # target critics
            forward(critic_shared)  # critic step
            backward(critic_shared, weights=True, first_input=False)
            forward(actor)  # actor step
            forward(critic_own)
            backward(critic_own, weights=False, first_input=True)  # d Q / d a only
            backward(actor, weights=True, first_input=False)

    return one_update


def batched(agents: list[AgentDims], algo: str = "cen-maddpg", **kw: object) -> BatchedMADDPG:
    """A BatchedMADDPG with the thesis settings (hidden 400-300); `kw`: lanes=...,
    precision=..."""
    return BatchedMADDPG(agents, LearnerSpec(algo=algo, hidden=HIDDEN), **kw)


def learner_pair(agents: list[AgentDims], algo: str) -> tuple[MADDPG, BatchedMADDPG, tuple]:
    """The reference learner, a BatchedMADDPG copy of it and a random minibatch: the
    same weights and data, so the two are timed on the same work."""
    reference = MADDPG(agents, LearnerSpec(algo=algo, hidden=HIDDEN))
    return reference, BatchedMADDPG.from_reference(reference), random_batch(reference)


def lanes_floor(m: BatchedMADDPG, lanes: Lanes) -> Callable[[], None]:
    """The same products with the rows split over the lanes, each lane its block."""
    parts = [floor_ops(m, b.stop - b.start) for b in lanes.blocks(BATCH)]
    return lambda: lanes.map(lambda part: part(), parts)


def bench_case(
    agents, algo: str, repeats: int, budget_s: float, lanes: bool = True, ref: bool = True
) -> dict[str, list[float]]:
    reference, fast, b = learner_pair(agents, algo)
    fns: dict[str, Callable[[], object]] = {"batched": lambda: fast.update(*b)}
    if ref:
        fns["ref"] = lambda: reference.update(*b)
    fns["floor"] = floor_ops(fast)
    if lanes:
        two = batched(agents, algo, lanes=2)
        two.load_state_dict(fast.state_dict())
        fns["lanes2"] = lambda: two.update(*b)
        fns["floor_lanes2"] = lanes_floor(fast, two.lanes)
    return measure(fns, repeats, budget_s)


def bench_bf16_case(
    agents: list[AgentDims], algo: str, repeats: int, budget_s: float, lanes: bool = True
) -> dict[str, list[float]]:
    """fp32 and bf16 updates of one learner state on one minibatch, and their floors (and
    bf16 without the fused kernel, and on two lanes), in the same rounds."""
    _, fast, b = learner_pair(agents, algo)
    low = batched(agents, algo, precision="bf16")
    low.load_state_dict(fast.state_dict())
    unfused = batched(agents, algo, precision="bf16", fused=False)
    unfused.load_state_dict(fast.state_dict())
    fns: dict[str, Callable[[], object]] = {
        "batched": lambda: fast.update(*b),
        "bf16": lambda: low.update(*b),
        "bf16_unfused": lambda: unfused.update(*b),
        "floor": floor_ops(fast),
        "floor_bf16": floor_ops(low),
    }
    if lanes:
        two = batched(agents, algo, lanes=2, precision="bf16")
        two.load_state_dict(fast.state_dict())
        fns["bf16_lanes2"] = lambda: two.update(*b)
    return measure(fns, repeats, budget_s)


def bf16_row(task: str, algo: str, n: int, threads: int, samples: dict[str, list[float]]) -> dict:
    """The bf16 table's row: medians of the rates, medians of the per-round ratios."""
    rate = {f"{k}_updates_per_s": 1 / statistics.median(v) for k, v in samples.items()}
    return {
        "task": task,
        "algo": algo,
        "agents": n,
        "threads": threads,
        **rate,
        "bf16_speedup": ratio(samples, "batched", "bf16"),
        "floor_bf16_speedup": ratio(samples, "floor", "floor_bf16"),
        "bf16_over_floor_bf16": ratio(samples, "bf16", "floor_bf16"),
        "fused_speedup": ratio(samples, "bf16_unfused", "bf16"),
        "bf16_unfused_over_floor_bf16": ratio(samples, "bf16_unfused", "floor_bf16"),
        "batched_over_floor": ratio(samples, "batched", "floor"),
        "bf16_lanes2_speedup": ratio(samples, "bf16", "bf16_lanes2"),
        "samples_s": samples,
    }


def cases_table(bench, make_row, repeats: int, budget_s: float, label: str = "") -> list[dict]:
    """Every case on one torch thread, then speaker_listener on two: the rows of one
    table (`bench` times a case, `make_row` summarises it)."""
    rows = []
    torch.set_num_threads(1)
    for task, n, algo, agents in CASES:
        progress(f"{label}{task} N={n} {algo} ...")
        rows.append(make_row(task, algo, n, 1, bench(agents, algo, repeats, budget_s)))
    torch.set_num_threads(2)
    progress(f"{label}speaker_listener, 2 threads ...")
    sl2 = bench(SPEAKER_LISTENER, "cen-maddpg", repeats, budget_s, lanes=False)
    rows.append(make_row("speaker_listener", "cen-maddpg", 2, 2, sl2))
    torch.set_num_threads(1)
    return rows


def bf16_table(repeats: int, budget_s: float) -> list[dict]:
    """Every case on one torch thread, then speaker_listener on two."""
    return cases_table(bench_bf16_case, bf16_row, repeats, budget_s, "bf16: ")


def print_bf16_table(rows: list[dict]) -> None:
    print(
        "\n| task | algo | N | torch threads | fp32 upd/s | bf16 upd/s | bf16 / fp32 speed "
        "| fp32 floor upd/s | bf16 floor upd/s | bf16 floor / fp32 floor speed "
        "| bf16 / bf16 floor time | fp32 / fp32 floor time | bf16 2 lanes upd/s "
        "| bf16 2 lanes / 1 lane speed | bf16 unfused upd/s | fused / unfused speed "
        "| unfused / bf16 floor time |"
    )
    print("|" + "---|" * 17)
    for r in rows:
        print(
            f"| {r['task']} | {r['algo']} | {r['agents']} | {r['threads']} "
            f"| {r['batched_updates_per_s']:.1f} | {r['bf16_updates_per_s']:.1f} "
            f"| {r['bf16_speedup']:.2f}x "
            f"| {r['floor_updates_per_s']:.1f} | {r['floor_bf16_updates_per_s']:.1f} "
            f"| {r['floor_bf16_speedup']:.2f}x | {r['bf16_over_floor_bf16']:.2f}x "
            f"| {r['batched_over_floor']:.2f}x "
            f"| {fmt(r.get('bf16_lanes2_updates_per_s'), '.1f')} "
            f"| {fmt(r['bf16_lanes2_speedup'], '.2f')}x "
            f"| {r['bf16_unfused_updates_per_s']:.1f} | {r['fused_speedup']:.2f}x "
            f"| {r['bf16_unfused_over_floor_bf16']:.2f}x |"
        )


def spin() -> None:
    """Keep one core busy (a stand-in for an actor, the counter or another user)."""
    while True:
        pass


def contention(repeats: int, budget_s: float) -> dict[str, list[float]]:
    """speaker_listener with another process spinning on one of the two cores: one lane,
    two lanes, and torch's own 2 intra-op threads (one lane)."""
    ctx = multiprocessing.get_context("spawn")
    hog = ctx.Process(target=spin, daemon=True)
    hog.start()
    try:
        time.sleep(0.2)
        one = batched(SPEAKER_LISTENER)
        two = batched(SPEAKER_LISTENER, lanes=2)
        b = random_batch(one)

        def threads2() -> None:
            torch.set_num_threads(2)
            try:
                one.update(*b)
            finally:
                torch.set_num_threads(1)

        auto = TunedMADDPG(batched(SPEAKER_LISTENER, lanes=2))
        fns = {"batched": lambda: one.update(*b), "lanes2": lambda: two.update(*b)}
        fns["threads2"] = threads2
        fns["auto"] = lambda: auto.update(*b)
        return measure(fns, repeats, budget_s)
    finally:
        hog.kill()
        hog.join()


def ratio(samples: dict[str, list[float]], a: str, b: str) -> float | None:
    """Median over rounds of time(a) / time(b)."""
    if a not in samples or b not in samples:
        return None
    return ratio_median(samples[a], samples[b])


def row(task: str, algo: str, n: int, threads: int, samples: dict[str, list[float]]) -> dict:
    """Medians of the rates, and medians of the ratios within each round."""
    rate = {f"{k}_updates_per_s": 1 / statistics.median(v) for k, v in samples.items()}
    return {
        "task": task,
        "algo": algo,
        "agents": n,
        "threads": threads,
        **rate,
        "batched_over_floor": ratio(samples, "batched", "floor"),
        "speedup_vs_ref": ratio(samples, "ref", "batched"),
        "lanes2_over_floor_lanes2": ratio(samples, "lanes2", "floor_lanes2"),
        "lanes2_speedup": ratio(samples, "batched", "lanes2"),
        "samples_s": samples,
    }


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(
        __doc__,
        "learner.json",
        " Batch 100, hidden 400-300, 1 torch thread (plus a 2-thread speaker_listener row).",
        prints="a markdown table",
    )
    parser.add_argument("--quick", action="store_true", help="3 rounds of ~0.05 s (smoke run)")
    parser.add_argument("--repeats", type=int, default=None, help="rounds per case (default 15)")
    parser.add_argument(
        "--precision",
        choices=("fp32", "bf16", "both"),
        default="both",
        help="which tables: the fp32 one (reference, batched, floors, lanes, one core busy), "
        "the bf16 one (fp32 vs bf16 updates and floors), or both (default)",
    )
    add_out(parser, "learner.json")
    args = parser.parse_args(argv)
    repeats = args.repeats or (3 if args.quick else 15)
    budget_s = 0.05 if args.quick else 0.15
    check_dims()
    load_before = os.getloadavg()
    result = {
        "command": command(__file__, argv),
        "batch": BATCH,
        "hidden": list(HIDDEN),
        "repeats": repeats,
        "torch": torch.__version__,
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "native_bf16": native_bf16(),
        "fused_kernel": fused_kernel() is not None,
        "loadavg_before": load_before,
    }
    if args.precision != "bf16":
        result.update(fp32_tables(repeats, budget_s))
    if args.precision != "fp32":
        if native_bf16():
            result["bf16_rows"] = bf16_table(repeats, budget_s)
            print_bf16_table(result["bf16_rows"])
        else:  # the learner would run fp32: nothing to compare
            print("\nbf16: skipped, this CPU has no native bf16 (the learner would run fp32)")
    result["loadavg_after"] = os.getloadavg()
    write_result(args.out, result, load_before)


def fp32_tables(repeats: int, budget_s: float) -> dict:
    """The fp32 table (every case, one thread, plus a 2-thread row) and the one-core-busy
    line, printed; their results."""
    rows = cases_table(bench_case, row, repeats, budget_s)
    progress("speaker_listener, one core busy ...")
    busy = contention(repeats, budget_s)

    head = (
        "| task | algo | N | torch threads | ref upd/s | batched upd/s | floor upd/s "
        "| batched/floor time | speedup vs ref | 2 lanes upd/s | 2-lane floor upd/s "
        "| 2 lanes / 2-lane floor time | 2 lanes / 1 lane speed |"
    )
    print(head)
    print("|" + "---|" * 13)
    for r in rows:
        print(
            f"| {r['task']} | {r['algo']} | {r['agents']} | {r['threads']} "
            f"| {r['ref_updates_per_s']:.1f} | {r['batched_updates_per_s']:.1f} "
            f"| {r['floor_updates_per_s']:.1f} | {r['batched_over_floor']:.2f}x "
            f"| {r['speedup_vs_ref']:.2f}x "
            f"| {fmt(r.get('lanes2_updates_per_s'), '.1f')} "
            f"| {fmt(r.get('floor_lanes2_updates_per_s'), '.1f')} "
            f"| {fmt(r['lanes2_over_floor_lanes2'], '.2f')}x "
            f"| {fmt(r['lanes2_speedup'], '.2f')}x |"
        )
    busy_rates = {k: 1 / statistics.median(v) for k, v in busy.items()}
    print(
        "\nspeaker_listener with another process spinning on one core (updates/s): "
        f"1 lane {busy_rates['batched']:.1f}, 2 lanes {busy_rates['lanes2']:.1f} "
        f"({ratio(busy, 'batched', 'lanes2'):.2f}x), torch 2 threads "
        f"{busy_rates['threads2']:.1f} ({ratio(busy, 'batched', 'threads2'):.2f}x), "
        f"lanes auto {busy_rates['auto']:.1f} ({ratio(busy, 'batched', 'auto'):.2f}x)"
    )
    return {"rows": rows, "one_core_busy": {"updates_per_s": busy_rates, "samples_s": busy}}


if __name__ == "__main__":
    main()
