"""Count store memory: bytes per run of the exact table against a count-min sketch
(`count_sketch`) as the keys grow, and the sketch's overestimates.

Memory: for each number of keys (default 10^5, 10^6, 10^7) and each store, a fresh
child process builds the run's exploration (speaker_listener, Cen-MACB, k = 512: one
table of 128-byte keys) and counts that many keys in chunks of 10,000; the figure is
the growth of its resident set (VmRSS from /proc, before counting and after), with the
store's own `memory_bytes()` beside it. Keys are synthetic: the run's SimHash of fresh
uniform random s||a vectors (`--keys simhash`, default up to 10^6), or uniform random
128-byte keys (`--keys random`, default at 10^7, where hashing 10^7 vectors would only
cost time): at k = 512 nearly every key of a real run is new, so either way N keys
are N transitions, each seen once. The exact table at 10^7 keys needs ~2 GB.

Error: on the same streams, each store's estimate of ~10,000 counted keys (the first
rows of every chunk, so early and late keys alike) against their true count (1), with
count-min's bound e / width x N; and on a real speaker-listener rollout (uniform random
actions, the thesis code's warm-up) hashed at k = 512 and k = 16 (keys repeat), the
estimate of every distinct key against the exact table, at the sketch's width and at
4096 and 256 (where collisions show).

    .venv/bin/python benchmarks/bench_sketch.py [--quick]

prints markdown tables and writes benchmarks/results/sketch.json. Memory, not time:
the numbers do not depend on the machine's load.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _harness import add_out, bench_parser, command, progress, write_result  # noqa: E402

CHUNK = 10_000
SAMPLE = 10_000
DEFAULT_SKETCH = {"memory_mb": 16, "depth": 4}  # width 2^20


def rss_bytes() -> int:
    """This process's resident set now (VmRSS)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def child(keys: int, store: str, source: str, sketch: dict[str, Any]) -> dict[str, Any]:
    """Count `keys` keys in one store of a fresh run; its memory and its estimates."""
    import numpy as np

    from shared.config import make_config
    from shared.envs.tasks import task_spec_for
    from shared.run.factories import build_exploration

    data: dict[str, Any] = {"explore": "cen-macb", "k": 512}
    if store == "sketch":
        data["count_sketch"] = sketch
    cfg = make_config(data)
    spec = task_spec_for(cfg)
    explorer = build_exploration(cfg, spec)
    table = explorer.tables[0]
    rng = np.random.default_rng(7)

    def chunk(n: int) -> np.ndarray:
        if source == "random":
            return rng.integers(0, 256, size=(n, table.key_bytes), dtype=np.uint8)
        obs = rng.uniform(-1, 1, (n, spec.joint_obs_dim)).astype(np.float32)
        act = rng.uniform(-1, 1, (n, spec.joint_act_dim)).astype(np.float32)
        return explorer.keys(obs, act)[0]

    chunks = -(-keys // CHUNK)
    last = keys - (chunks - 1) * CHUNK  # the last chunk's rows, the fewest
    per_chunk = max(1, min(last, SAMPLE // chunks))
    sample = np.ones((chunks * per_chunk, table.key_bytes), np.uint8)  # touched: resident
    chunk(CHUNK)  # the allocator's arenas at their working size before measuring
    before = rss_bytes()
    t0 = time.perf_counter()
    done = 0
    for c in range(chunks):
        part = chunk(min(CHUNK, keys - done))
        table.increment(part)
        sample[c * per_chunk : (c + 1) * per_chunk] = part[:per_chunk]
        done += len(part)
    seconds = time.perf_counter() - t0
    after = rss_bytes()
    est = table.counts(sample)  # keys from the whole stream, all distinct: n = 1
    return {
        "keys": keys,
        "store": store,
        "source": source,
        "distinct": len(table),
        "rss_growth_bytes": after - before,
        "memory_bytes": table.memory_bytes(),
        "rss_bytes_per_key": (after - before) / keys,
        "overestimate_mean": float(est.mean() - 1),
        "overestimate_max": int(est.max() - 1),
        "seconds": seconds,  # for the record only: not a timing benchmark
    }


def run_child(keys: int, store: str, source: str, sketch: dict[str, Any]) -> dict[str, Any]:
    argv = [sys.executable, __file__, "--child", json.dumps([keys, store, source, sketch])]
    proc = subprocess.run(argv, capture_output=True, text=True, check=False, cwd=ROOT)
    if proc.returncode != 0:
        raise RuntimeError(f"{store} at {keys} keys failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def real_stream_errors(steps: int, sketch: dict[str, Any]) -> list[dict[str, Any]]:
    """Each distinct key's estimate against its exact count on a real rollout."""
    import numpy as np

    from shared.config import make_config
    from shared.core.counting import CountSketch, CountTable, sketch_bound
    from shared.envs.tasks import make_task_for, task_spec_for
    from shared.run.factories import build_exploration
    from shared.run.rollout import make_collector

    out = []
    for k in (512, 16):
        cfg = make_config(
            {"explore": "cen-macb", "k": k, "warmup": "random", "learning_starts": 10**9}
        )
        collector = make_collector(cfg, make_task_for(cfg))
        rows = [collector.step(lambda obs: obs) for _ in range(steps)]
        explorer = build_exploration(cfg, task_spec_for(cfg))
        keys = explorer.keys(np.stack([r.obs for r in rows]), np.stack([r.act for r in rows]))[0]
        exact = CountTable(keys.shape[1])
        exact.increment(keys)
        _, first = np.unique(keys, axis=0, return_index=True)
        distinct = keys[np.sort(first)]
        true = exact.counts(distinct)
        shape = make_config({"count_sketch": sketch}).count_sketch
        assert shape is not None
        for width in (shape.columns, 4096, 256):
            eps, delta = sketch_bound(width, shape.depth)
            for conservative in (True, False):
                table = CountSketch(keys.shape[1], width, shape.depth, 0, conservative)
                table.increment(keys)
                err = table.counts(distinct) - true
                out.append(
                    {
                        "k": k,
                        "transitions": steps,
                        "distinct_keys": len(distinct),
                        "width": width,
                        "depth": shape.depth,
                        "update": "conservative" if conservative else "plain",
                        "bound_eps_n": eps * steps,
                        "delta": delta,
                        "under_true": int(np.count_nonzero(err < 0)),
                        "share_over_true": float(np.mean(err > 0)),
                        "share_over_bound": float(np.mean(err > eps * steps)),
                        "overestimate_mean": float(err.mean()),
                        "overestimate_max": int(err.max()),
                    }
                )
    return out


def main(argv: list[str] | None = None) -> None:
    parser = bench_parser(__doc__, "sketch.json")
    parser.add_argument("--quick", action="store_true", help="10^4 and 10^5 keys only")
    parser.add_argument(
        "--keys", type=int, nargs="+", default=None, help="key counts (default 1e5 1e6 1e7)"
    )
    parser.add_argument(
        "--random-from",
        type=int,
        default=10**7,
        help="from this many keys on, random key bytes instead of SimHash keys",
    )
    parser.add_argument(
        "--sketch", type=json.loads, default=DEFAULT_SKETCH, help="count_sketch as JSON"
    )
    parser.add_argument("--steps", type=int, default=20_000, help="real rollout transitions")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    add_out(parser, "sketch.json")
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(*json.loads(args.child))))
        return
    counts = args.keys or ([10**4, 10**5] if args.quick else [10**5, 10**6, 10**7])
    load = __import__("os").getloadavg()
    rows = []
    for n in counts:
        source = "random" if n >= args.random_from else "simhash"
        for store in ("exact", "sketch"):
            progress(f"{store}: {n} keys ({source}) ...")
            rows.append(run_child(n, store, source, args.sketch))
    progress("real speaker-listener streams ...")
    errors = real_stream_errors(2000 if args.quick else args.steps, args.sketch)

    print("| keys | key source | store | RSS growth (MB) | bytes per key | memory_bytes (MB) |"
          " mean overestimate | max |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['keys']:,} | {r['source']} | {r['store']} | "
            f"{r['rss_growth_bytes'] / 2**20:,.1f} | {r['rss_bytes_per_key']:.1f} | "
            f"{r['memory_bytes'] / 2**20:,.1f} | {r['overestimate_mean']:.3f} | "
            f"{r['overestimate_max']} |"
        )
    print()
    print("| k | transitions | distinct keys | width x depth | update | bound e/w*N | "
          "share > true | share > bound | mean over | max over |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|")
    for e in errors:
        print(
            f"| {e['k']} | {e['transitions']:,} | {e['distinct_keys']:,} | "
            f"{e['width']} x {e['depth']} | {e['update']} | {e['bound_eps_n']:.2f} | "
            f"{e['share_over_true']:.4f} | {e['share_over_bound']:.4f} | "
            f"{e['overestimate_mean']:.3f} | {e['overestimate_max']} |"
        )
    sketch = args.sketch
    result = {
        "command": command(__file__, argv),
        "sketch": sketch,
        "sketch_bound": {
            "eps_per_transition": math.e / (make_width(sketch)),
        },
        "memory": rows,
        "real_stream": errors,
    }
    write_result(args.out, result, load)


def make_width(sketch: dict[str, Any]) -> int:
    from shared.config import make_config

    shape = make_config({"count_sketch": sketch}).count_sketch
    assert shape is not None
    return shape.columns


if __name__ == "__main__":
    main()
