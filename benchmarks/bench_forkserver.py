"""Starting the cluster and restarting a service: forked from the fork server
(cli/forkserver.py) against an interpreter per service (MACB_FORK_SERVER=0).

Each round starts the plan `macb up` starts (router, counter, learner, evaluator and one
actor; no API) with cli.supervisor.Cluster, as `macb up` does, and times: the start,
until every service answers on the bus (its info, as `macb ps` asks); then a restart:
the learner is SIGKILLed, the supervisor restarts it, and the time until it answers
again. Also the CPU seconds the cluster's processes used from start to stop (theirs and
the fork server's, which loads torch once per cluster). Variants alternate A B / B A
over rounds, and each round's fork/exec ratio is reported with its median.
"""

from __future__ import annotations

import os
import resource
import shutil
import signal
import tempfile
import time
from pathlib import Path

from _procs import pin_threads

pin_threads()

from _harness import add_out, begin_run, bench_parser, command, progress, write_result  # noqa: E402
from _stats import cpu_model, fmt, median, ratio_median, rotating_rounds  # noqa: E402

from cli import forkserver  # noqa: E402
from cli.supervisor import Cluster, cluster_plan, free_port, wait_port  # noqa: E402
from shared import procs  # noqa: E402
from shared.net.bus import Bus  # noqa: E402
from shared.net.control import discover  # noqa: E402

RESULT = "forkserver.json"
VARIANTS = ("exec", "fork")


def _children_cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def _answering(bus: Bus, ids: set[str], timeout: float) -> None:
    """Until every one of `ids` answers with its info."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if ids <= {i["id"] for i in discover(bus, timeout=0.5)}:
            return
        time.sleep(0.02)
    raise TimeoutError(f"{sorted(ids)} did not all answer within {timeout:g} s")


def one_round(variant: str, work: Path, timeout: float) -> dict[str, float]:
    os.environ["MACB_FORK_SERVER"] = "1" if variant == "fork" else "0"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    plan = cluster_plan(1, endpoint, str(work / "data"), api=None)
    cluster = Cluster(plan, work / "logs", echo=False)
    cpu0, t0 = _children_cpu(), time.monotonic()
    cluster.start()
    try:
        wait_port(endpoint)
        with Bus([endpoint]) as bus:
            ids = {s.name for s in plan if s.name != "router"}
            _answering(bus, ids, timeout)
            start_s = time.monotonic() - t0
            old = cluster.procs["learner"].pid
            procs.send(old, signal.SIGKILL)
            t1 = time.monotonic()
            while not any(  # the learner again, as its restart (MACB_RESTARTS) says
                i["id"] == "learner" and i.get("restarts", 0) >= 1
                for i in discover(bus, timeout=0.5)
            ):
                cluster.supervise()
                time.sleep(0.02)
                if time.monotonic() - t1 > timeout:
                    raise TimeoutError("the learner did not come back")
            restart_s = time.monotonic() - t1
    finally:
        cluster.stop()
    cpu = _children_cpu() - cpu0
    return {"start_s": start_s, "restart_s": restart_s, "cpu_s": cpu}


def main(argv: list[str] | None = None) -> int:
    p = bench_parser(__doc__, RESULT)
    p.add_argument("--rounds", type=int, default=6, help="rounds per variant")
    p.add_argument("--timeout", type=float, default=120)
    p.add_argument("--quick", action="store_true", help="1 round per variant")
    add_out(p, RESULT)
    args = p.parse_args(argv)
    if args.quick:
        args.rounds = 1
    load_before = os.getloadavg()
    root = Path(tempfile.mkdtemp(prefix="bench-forkserver-"))
    runs: dict[str, list[dict]] = {v: [] for v in VARIANTS}
    for r, variant in rotating_rounds(args.rounds, VARIANTS):
        work = root / f"{variant}-{r}"
        load = begin_run(work, f"round {r}: {variant}")
        res = one_round(variant, work, args.timeout)
        res["load"] = load
        runs[variant].append(res)
        progress(
            f"  start {res['start_s']:.2f} s, learner restart {res['restart_s']:.2f} s, "
            f"{res['cpu_s']:.1f} CPU-s"
        )
    os.environ.pop("MACB_FORK_SERVER", None)
    forkserver.close_shared()
    shutil.rmtree(root)
    table = {}
    for key in ("start_s", "restart_s", "cpu_s"):
        table[key] = {
            **{v: median([x[key] for x in runs[v]]) for v in VARIANTS},
            "ratio_fork_exec": ratio_median(
                [x[key] for x in runs["fork"]], [x[key] for x in runs["exec"]]
            ),
        }
    cpu = cpu_model()
    print(f"{cpu}: medians of {args.rounds} rounds per variant (ratio: within each round)")
    print(f"{'':12} {'exec':>8} {'fork':>8} {'fork/exec':>10}")
    for key, row in table.items():
        cells = [fmt(row[k], "8.2f") for k in ("exec", "fork")]
        print(f"{key:12} {' '.join(cells)} {fmt(row['ratio_fork_exec'], '10.2f')}")
    write_result(
        args.out,
        {"command": command(__file__, argv), "cpu": cpu, "rounds": runs, "median": table},
        load_before,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
