"""What the secure bus costs: the cluster's training throughput with TLS, user/password
and the router's ACL against plain TCP, and the learner's bonus-query round trip.

The workload is bench_e2e's (the thesis's speaker_listener arm: Cen-MADDPG + Cen-MACB,
k=512, beta 0.8, batch 100, hidden 400-300), run by `macb up --run` as a user would,
with evaluation only at the end so the bus's share of the work is largest. Variants,
alternated A B / B A over rounds: `plain` (tcp/ on loopback, no credentials, today's
default) and `secure` (`macb up --secrets DIR`: tls/ on every link, every service
signed in as its own user, the router enforcing the ACL and reading its log for
denials). Reported per variant: the steady-state updates/s (= training steps/s at
replay ratio 1), its ratio secure/plain within each round (the target: >= 0.95), and
the bonus query's p50/p99 as the learner times it (round trip through the router) and
as the counter times it (answering only). Secrets are made by `macb certs` in the
work directory. Processes are ended by PID; ports are free loopback ports.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from _harness import add_out, begin_run, bench_parser, command, macb_argv, progress, write_result
from _stats import fmt, median, ratio_median, rotating_rounds
from bench_e2e import CONFIG_YAML, run_cluster

from shared.net.security import ENV

RESULT = "secure.json"
VARIANTS = ("plain", "secure")
TARGET_RATIO = 0.95


def run(variant: str, config: Path, secrets: Path, args, work: Path) -> dict:
    """One `macb up --run` of the variant; the security variables only for `secure`."""
    for key in (ENV["secrets"], ENV["user"]):
        os.environ.pop(key, None)
    extra: tuple = ()
    if variant == "secure":
        os.environ[ENV["secrets"]] = str(secrets)
        os.environ[ENV["user"]] = "cli"  # the benchmark's own watcher session
        extra = ("--secrets", str(secrets))
    try:
        return run_cluster(config, args.episodes, args.episodes, 1, work, args.timeout, extra)
    finally:
        for key in (ENV["secrets"], ENV["user"]):
            os.environ.pop(key, None)


def query_latency(secrets: Path | None, queries: int, rows: int, work: Path) -> dict:
    """Bonus-query round trips through a router process, plain or secure: a queryable
    signed in as `counter` answers every query with a reply the size of a real one
    (counts int64 and bonuses float32 per row) and a querier signed in as `learner`
    sends the learner's tick query (`rows` rows of speaker_listener's joint obs and
    action, float32), both sessions in this process. The bus alone: no hashing."""
    import numpy as np
    from _procs import end, start, thread_env

    from cli.supervisor import free_port, wait_port
    from shared.net.bus import Bus, k_bonus
    from shared.net.messages import BonusQuery, BonusReply
    from shared.net.security import Security
    from shared.net.wire import encode

    proto = "tls" if secrets else "tcp"
    endpoint = f"{proto}/127.0.0.1:{free_port()}"
    env = thread_env(True)
    for key in ENV.values():
        env.pop(key, None)
    if secrets:
        env.update({ENV["secrets"]: str(secrets), ENV["user"]: "router"})
    router = start(macb_argv("serve", "router", "--listen", endpoint), work / "router.log", env)
    try:
        wait_port(endpoint)

        def sec(user: str) -> Security:
            if not secrets:
                return Security()
            return Security.from_env({ENV["secrets"]: str(secrets), ENV["user"]: user})

        rng = np.random.default_rng(0)
        query = encode(
            BonusQuery(
                "r",
                obs=rng.random((rows, 14), dtype=np.float32),
                act=rng.random((rows, 8), dtype=np.float32),
            )
        )
        reply = encode(
            BonusReply(
                "r",
                counts=np.ones((1, rows), dtype=np.int64),
                bonus=np.ones((rows, 2), dtype=np.float32),
            )
        )
        with Bus([endpoint], security=sec("counter")) as counter:
            counter.queryable(k_bonus("*"), lambda key, payload: reply)
            with Bus([endpoint], security=sec("learner")) as learner:
                import time

                deadline = time.monotonic() + 10
                while not learner.get(k_bonus("r"), query, timeout=1.0):
                    if time.monotonic() > deadline:
                        raise RuntimeError("the queryable does not answer")
                times = []
                for _ in range(queries):
                    t0 = time.perf_counter()
                    got = learner.get(k_bonus("r"), query, timeout=2.0)
                    times.append((time.perf_counter() - t0) * 1e3)
                    if not got:
                        raise RuntimeError("a query got no reply")
        times.sort()
        return {
            "p50_ms": times[len(times) // 2],
            "p99_ms": times[int(len(times) * 0.99)],
            "query_bytes": len(query),
            "reply_bytes": len(reply),
        }
    finally:
        end(router)


def main(argv: list[str] | None = None) -> int:
    p = bench_parser(__doc__, RESULT)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--episodes", type=int, default=150, help="training episodes per run")
    p.add_argument("--timeout", type=float, default=900)
    p.add_argument("--quick", action="store_true", help="2 rounds of 40 episodes")
    p.add_argument("--queries", type=int, default=500, help="per round of the latency part")
    p.add_argument("--rows", type=int, default=2000, help="rows per bonus query")
    p.add_argument("--skip-cluster", action="store_true", help="only the latency part")
    add_out(p, RESULT)
    args: argparse.Namespace = p.parse_args(argv)
    if args.quick:
        args.rounds, args.episodes = 2, 40
    load_before = os.getloadavg()
    runs: dict[str, list[dict]] = {v: [] for v in VARIANTS}
    root = Path(tempfile.mkdtemp(prefix="bench-secure-"))  # kept if a run fails: its logs
    secrets = root / "secrets"
    subprocess.run(macb_argv("certs", str(secrets)), check=True, capture_output=True)
    config = root / "config.yaml"
    config.write_text(CONFIG_YAML)
    latency: dict[str, list[dict]] = {v: [] for v in VARIANTS}
    for r, variant in rotating_rounds(max(args.rounds, 3), VARIANTS):
        work = root / f"latency-{variant}-{r}"
        work.mkdir()
        lat = query_latency(secrets if variant == "secure" else None, args.queries, args.rows, work)
        lat["load"] = os.getloadavg()
        latency[variant].append(lat)
        progress(
            f"latency round {r}: {variant} p50 {lat['p50_ms']:.3f} ms, p99 {lat['p99_ms']:.3f}"
        )
    for r, variant in rotating_rounds(0 if args.skip_cluster else args.rounds, VARIANTS):
        work = root / f"{variant}-{r}"
        load = begin_run(work, f"round {r}: {variant}, {args.episodes} episodes")
        res = run(variant, config, secrets, args, work)
        res["load"] = load
        runs[variant].append(res)
        shutil.rmtree(work)
        lrn = res["learner"]
        progress(
            f"  {res['steady']['rate'] or 0:.1f} updates/s, bonus query p50 "
            f"{lrn.get('bonus_p50_ms')} ms, p99 {lrn.get('bonus_p99_ms')} ms"
        )
    lat_summary = {
        v: {
            "p50_ms": median(x["p50_ms"] for x in latency[v]),
            "p99_ms": median(x["p99_ms"] for x in latency[v]),
        }
        for v in VARIANTS
    }
    q = latency["plain"][0]
    print(
        f"\nbonus query round trip, the bus alone ({args.rows} rows: {q['query_bytes']} bytes "
        f"in, {q['reply_bytes']} out; median of {len(latency['plain'])} rounds of "
        f"{args.queries}):\n\n| variant | p50 (ms) | p99 (ms) |\n|---|---|---|"
    )
    for v in VARIANTS:
        print(f"| {v} | {lat_summary[v]['p50_ms']:.3f} | {lat_summary[v]['p99_ms']:.3f} |")
    if args.skip_cluster:
        shutil.rmtree(root)
        result = {"command": command(__file__, argv), "latency": latency}
        write_result(args.out, result | {"latency_summary": lat_summary}, load_before)
        return 0
    rate = {v: [x["steady"]["rate"] for x in runs[v]] for v in VARIANTS}
    summary = {
        v: {
            "updates_per_s": median(rate[v]),
            "bonus_p50_ms": median(x["learner"].get("bonus_p50_ms") for x in runs[v]),
            "bonus_p99_ms": median(x["learner"].get("bonus_p99_ms") for x in runs[v]),
            "counter_query_p50_ms": median(x["counter"].get("query_p50_ms") for x in runs[v]),
            "counter_query_p99_ms": median(x["counter"].get("query_p99_ms") for x in runs[v]),
            "replay_ratio": median(x["learner"].get("replay_ratio") for x in runs[v]),
        }
        for v in VARIANTS
    }
    ratios = [s / b for s, b in zip(rate["secure"], rate["plain"], strict=True)]
    ratio = ratio_median(rate["secure"], rate["plain"])
    print("\n| variant | updates/s (median) | bonus query p50 / p99 (learner, ms) "
          "| counter answers p50 / p99 (ms) | replay ratio |")  # fmt: skip
    print("|---|---|---|---|---|")
    for v in VARIANTS:
        s = summary[v]
        print(
            f"| {v} | {fmt(s['updates_per_s'])} | {fmt(s['bonus_p50_ms'], '.2f')} / "
            f"{fmt(s['bonus_p99_ms'], '.2f')} | {fmt(s['counter_query_p50_ms'], '.2f')} / "
            f"{fmt(s['counter_query_p99_ms'], '.2f')} | {fmt(s['replay_ratio'], '.3f')} |"
        )
    # A round's ratio moves with the machine's load: when the rounds disagree by more
    # than the target's margin, their median does not resolve it either way.
    spread = max(ratios) / min(ratios) if ratios and min(ratios) > 0 else float("inf")
    verdict = "met" if ratio >= TARGET_RATIO else "NOT met"
    if spread > 1 + 2 * (1 - TARGET_RATIO):
        verdict = f"not resolved: the rounds' ratios spread {min(ratios):.2f}-{max(ratios):.2f}"
    print(
        f"\nsecure / plain, per round: {', '.join(f'{x:.3f}' for x in ratios)}; median "
        f"{ratio:.3f} (target >= {TARGET_RATIO}: {verdict})"
    )
    result = {
        "command": command(__file__, argv),
        "episodes": args.episodes,
        "rounds": args.rounds,
        "summary": summary,
        "ratio_secure_over_plain": ratio,
        "ratios": ratios,
        "latency_summary": lat_summary,
        "latency": latency,
        "target_ratio": TARGET_RATIO,
        "runs": runs,
    }
    write_result(args.out, result, load_before)
    shutil.rmtree(root)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
