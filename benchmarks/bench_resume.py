"""Learner resume in the supervised cluster: how long a SIGKILLed learner keeps a run waiting.

Each round starts the cluster as `macb up` does (cli/supervisor.py's plan and `Cluster`,
whose `supervise` restarts a dead service), runs speaker_listener at thesis settings
(Cen-MADDPG + Cen-MACB, k 512, beta 0.8, 400-300, batch 100), SIGKILLs the learner
once `--kill-at` episodes are in, and times, from the restart: the resumed learner's
status (cut loaded, log read), its first update, and the next evaluation point. The
learner's own stats give what its cuts cost (time, bytes, share of its wall time at
the cut interval in use). The run must still complete exactly (counted == collected,
replay ratio 1.000).

Target (issue 14): the run continues within 10 s of the restart.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from _procs import pin_threads

pin_threads()

from _harness import (  # noqa: E402
    THESIS_ARM,
    add_out,
    begin_run,
    bench_parser,
    command,
    progress,
    write_result,
)
from _stats import fmt, median  # noqa: E402

from cli.supervisor import Cluster, cluster_plan, free_port, wait_port  # noqa: E402
from shared.config import make_config  # noqa: E402
from shared.net.bus import Bus, k_weights  # noqa: E402
from shared.net.control import discover, start_run  # noqa: E402
from shared.net.messages import Weights  # noqa: E402
from shared.net.wire import decode  # noqa: E402

THESIS = {
    **THESIS_ARM,
    "hidden": [400, 300],
    "batch_size": 100,
    "eval_every": 25,
}


def one_round(work: Path, episodes: int, kill_at: int, cut_s: float, seed: int) -> dict:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    os.environ["MACB_LEARNER_CUT_S"] = str(cut_s)
    cluster = Cluster(cluster_plan(1, endpoint, str(work / "data"), api=None), work / "logs", False)
    cluster.start()
    try:
        wait_port(endpoint)
        with Bus([endpoint]) as bus:
            deadline = time.monotonic() + 90
            while len(discover(bus)) < 4:
                assert time.monotonic() < deadline, "services did not come up"
                time.sleep(0.2)
            config = make_config({**THESIS, "episodes": episodes, "seed": seed})
            updates_seen: list[tuple[float, int]] = []  # (arrival, updates) of weights

            def on_weights(key: str, payload: bytes) -> None:
                msg = decode(payload, Weights)
                updates_seen.append((time.monotonic(), msg.updates))

            bus.subscribe(k_weights("*", "*"), on_weights)
            watch = start_run(bus, config, actors=1)
            while watch.latest.get("learner", {}).get("episodes_ingested", 0) < kill_at:
                assert watch.state() == "running", watch.states
                time.sleep(0.05)
            at_kill = len(watch.rows)
            old = cluster.procs["learner"]
            t_kill = time.monotonic()
            old.kill()
            old.wait()
            t_restart = resumed_t = first_update_t = next_point_t = None
            resumed: dict = {}
            while watch.state() == "running":
                cluster.supervise()
                now = time.monotonic()
                if t_restart is None and cluster.procs["learner"] is not old:
                    t_restart = now
                learner = watch.states.get("learner", {})
                if resumed_t is None and isinstance(learner.get("resumed"), dict):
                    resumed_t, resumed = now, learner["resumed"]
                if resumed_t and first_update_t is None:
                    first_update_t = next(
                        (t for t, u in updates_seen if t > t_restart and u > resumed["updates"]),
                        None,
                    )
                if next_point_t is None and len(watch.rows) > at_kill:
                    next_point_t = now
                time.sleep(0.02)
            assert watch.state() == "completed", watch.states
            time.sleep(1.5)  # the counter's final stats
            final = watch.states["learner"]
            counted = watch.latest["counter"]["counted_transitions"]
    finally:
        cluster.stop()
    collected = episodes * config.episode_len
    assert counted == collected == final["ingested"], (counted, collected, final["ingested"])
    assert final["replay_ratio"] == 1.0, final["replay_ratio"]
    assert t_restart is not None and resumed_t is not None and first_update_t is not None
    return {
        "restart_after_kill_s": t_restart - t_kill,
        "resumed_after_restart_s": resumed_t - t_restart,
        "first_update_after_restart_s": first_update_t - t_restart,
        "next_point_after_kill_s": (next_point_t - t_kill) if next_point_t else None,
        "resumed": resumed,
        "cut_ms_mean_after_resume": final["cut_ms_mean"],
        "cut_bytes": final["cut_bytes"],
        "cuts_after_resume": final["cuts"],
        "wall_s_after_resume": final["wall_s"],
        "cut_share_at_interval": final["cut_ms_mean"] / 1e3 / cut_s,
        "counted": counted,
        "replay_ratio": final["replay_ratio"],
    }


def main(argv: list[str] | None = None) -> int:
    parser = bench_parser(__doc__, "resume.json")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=300)
    parser.add_argument("--kill-at", type=int, default=150, help="episodes in when killed")
    parser.add_argument("--cut-s", type=float, default=30.0, help="MACB_LEARNER_CUT_S")
    parser.add_argument("--quick", action="store_true", help="1 round, 60 episodes, small nets")
    add_out(parser, "resume.json")
    args = parser.parse_args(argv)
    if args.quick:
        args.rounds, args.episodes, args.kill_at, args.cut_s = 1, 60, 30, 1.0
        THESIS.update(hidden=[32, 32], batch_size=16, k=64)
    load = os.getloadavg()
    rounds = []
    for r in range(args.rounds):
        work = Path(os.environ.get("TMPDIR", "/tmp")) / f"bench-resume-{os.getpid()}-{r}"
        begin_run(work, f"round {r + 1}/{args.rounds}")
        rounds.append(one_round(work, args.episodes, args.kill_at, args.cut_s, seed=r))
        progress(f"  {rounds[-1]}")
    keys = (
        "restart_after_kill_s",
        "resumed_after_restart_s",
        "first_update_after_restart_s",
        "next_point_after_kill_s",
        "cut_ms_mean_after_resume",
    )
    summary = {k: median(r[k] for r in rounds) for k in keys}
    print(
        "| restart after kill | resumed after restart | first update after restart | "
        "next point after kill | cut (ms) | cut file | share at interval |"
    )
    print("|---|---|---|---|---|---|---|")
    print(
        f"| {fmt(summary['restart_after_kill_s'], '.2f')} s "
        f"| {fmt(summary['resumed_after_restart_s'], '.2f')} s "
        f"| {fmt(summary['first_update_after_restart_s'], '.2f')} s "
        f"| {fmt(summary['next_point_after_kill_s'], '.2f')} s "
        f"| {fmt(summary['cut_ms_mean_after_resume'], '.1f')} "
        f"| {rounds[-1]['cut_bytes'] / 1e6:.2f} MB "
        f"| {100 * median(r['cut_share_at_interval'] for r in rounds):.3f}% |"
    )
    write_result(
        args.out,
        {
            "command": command(__file__, argv),
            "args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
            "rounds": rounds,
            "median": summary,
        }
        | {"out": str(args.out)},
        load,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
