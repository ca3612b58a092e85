"""API read latency: GET /runs/{id}/metrics on a run with 10,000 stored points.

Fills a real SQLite store (WAL, as the API keeps it) with one experiment whose run
has N metric points with every field the evaluator sends, starts the real app with
uvicorn on a loopback port (`macb serve api` in its own process, scheduler off:
nothing else touches the store), and times real HTTP GETs from this process with
one keep-alive httpx client:

* `all`: GET /runs/{id}/metrics (every point, the default limit covers 10,000);
* `incremental`: GET /runs/{id}/metrics?since=N-10 (the last 10 points: a poller);
* `csv`: GET /runs/{id}/metrics.csv;
* `run`: GET /runs/{id}.

Each request is timed from send to the last byte received; p50 and p99 over the
requests (after a warm-up). Results go to benchmarks/results/api.json.

    .venv/bin/python benchmarks/bench_api.py [--points 10000] [--requests 200]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import random
import statistics
import sys
import tempfile
import time
from pathlib import Path

import httpx
from _harness import RESULTS, macb_argv
from _procs import end, start

from cli.supervisor import free_port
from services.api.store import Store

CONFIG = {"task": "speaker_listener", "episodes": 100_000, "eval_every": 10}


def fill(db: Path, points: int) -> str:
    store = Store(db)
    store.create_experiment(
        "xbench",
        "bench",
        {"config": CONFIG, "seeds": [0], "grid": None, "actors": 1},
        [{"id": "xbench-0", "seed": 0, "point": {}, "config": CONFIG, "actors": 1}],
    )
    rng = random.Random(0)
    rows = []
    for i in range(1, points + 1):
        rows.append(
            {
                "episode": 10 * i,
                "env_steps": 200 * i,
                "success_rate": rng.random(),
                "eval_return": -rng.random() * 20,
                "collisions_cum": i * 3,
                "count1_pct": rng.random() * 100,
                "table_size": 50 * i,
                "counted_transitions": 200 * i,
                "steps_per_sec": 400 + rng.random() * 50,
                "train_steps_per_sec": 450 + rng.random() * 50,
                "updates": 200 * i - 100,
                "wall_s": i * 0.5,
                "replay_ratio": 1.0,
                "policy_lag": rng.random() * 2,
                "policy_version": 10 * i,
            }
        )
    for i in range(0, points, 1000):  # as the scheduler writes: batches as rows arrive
        store.add_points("xbench-0", rows[i : i + 1000])
    store.close()
    return "xbench-0"


def timed(client: httpx.Client, path: str, n: int, warmup: int = 10) -> dict[str, float]:
    for _ in range(warmup):
        client.get(path).raise_for_status()
    times = []
    size = 0
    for _ in range(n):
        t0 = time.perf_counter()
        r = client.get(path)
        r.raise_for_status()
        size = len(r.content)
        times.append(time.perf_counter() - t0)
    times.sort()
    return {
        "p50_ms": 1e3 * statistics.median(times),
        "p99_ms": 1e3 * times[min(len(times) - 1, int(0.99 * len(times)))],
        "mean_ms": 1e3 * statistics.fmean(times),
        "bytes": size,
        "requests": n,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=10_000)
    ap.add_argument("--requests", type=int, default=200)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "api.sqlite3"
        t0 = time.perf_counter()
        run = fill(db, args.points)
        fill_s = time.perf_counter() - t0
        port = free_port()
        argv = macb_argv("serve", "api", "--listen-http", f"127.0.0.1:{port}")
        argv += ["--db", str(db), "--data-dir", tmp]
        server = start(argv, env={**os.environ, "MACB_API_SCHEDULER": "false"})
        try:
            client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30)
            deadline = time.monotonic() + 60
            while True:
                try:
                    client.get("/health").raise_for_status()
                    break
                except httpx.HTTPError:
                    if time.monotonic() > deadline or server.poll() is not None:
                        raise
                    time.sleep(0.1)
            page = client.get(f"/runs/{run}/metrics").json()
            assert len(page["points"]) == args.points and not page["more"]
            results = {
                "all": timed(client, f"/runs/{run}/metrics", args.requests),
                "incremental": timed(
                    client, f"/runs/{run}/metrics?since={args.points - 10}", args.requests
                ),
                "csv": timed(client, f"/runs/{run}/metrics.csv", max(20, args.requests // 4)),
                "run": timed(client, f"/runs/{run}", args.requests),
            }
            client.close()
        finally:
            end(server)
    out = {
        "points": args.points,
        "fill_s": fill_s,
        "results": results,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
    }
    print(f"GET /runs/{{id}}/metrics on a run with {args.points} stored points")
    print("| request | p50 ms | p99 ms | mean ms | response bytes |")
    print("|---|---:|---:|---:|---:|")
    for name, r in results.items():
        print(
            f"| {name} | {r['p50_ms']:.2f} | {r['p99_ms']:.2f} | {r['mean_ms']:.2f} "
            f"| {r['bytes']} |"
        )
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "api.json").write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
