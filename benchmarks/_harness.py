"""What the benchmarks share beyond timing and processes: the CLI, clusters, runs, results.

The benchmarks measure the platform's own code paths, so they start services the way
`macb up` does (cli/supervisor.py's `cluster_plan` and `Cluster`), follow runs with
shared/net/control.py's `RunWatch` and ask the bus by shared/net/bus.py's key functions rather
than keeping copies of them that drift. The command line and the exploration factory
are named here once, so a move of either (`python -m cli`, `shared.run.factories`) is one
edit for every benchmark. Importing this loads numpy (the bus codec) but not torch or
the environments: the counter benchmark's publisher processes import it and start fast.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from _procs import ROOT, Procs

from cli.supervisor import Cluster, ServiceSpec
from shared.net.bus import Bus
from shared.net.control import RunWatch
from shared.net.messages import Assignment

RESULTS = ROOT / "benchmarks" / "results"
# The thesis's speaker_listener arm (figure 8's sparse Cen-MACB; appendix A's networks
# and batch are the config defaults): what the learner-side benchmarks run.
THESIS_ARM = {
    "task": "speaker_listener",
    "algo": "cen-maddpg",
    "explore": "cen-macb",
    "k": 512,
    "beta": 0.8,
}
CLI_MODULE = "cli"  # what `macb` runs: `python -m cli ...`
# Env steps of figure 8's headline pair (sparse and sparse Cen-MACB): 2 arms x 3 seeds x
# configs/fig8's episodes x episode_len (tests/test_benchmarks.py checks it), the length
# bench_group's and bench_slots' projections in hours are of.
FIG8_PAIR_RUN_STEPS = 2 * 3 * 40_000 * 20


def macb_argv(*args: str, profile: Path | None = None) -> list[str]:
    """`macb ARGS` as this interpreter runs it; under cProfile (writing `profile`) if
    given, which sees the main thread (a service's loop), not Zenoh's."""
    prof = ["-m", "cProfile", "-o", str(profile)] if profile else []
    return [sys.executable, *prof, "-m", CLI_MODULE, *args]


class Services:
    """A cluster_plan's services, started as `macb up` starts them (cli.supervisor.Cluster:
    router first, then the rest), except those named in `profile`, which run under
    cProfile in a process of their own once the others are up. The router cannot be
    profiled: the cluster waits until it listens."""

    def __init__(
        self, plan: list[ServiceSpec], log_dir: Path, profile: dict[str, Path] | None = None
    ) -> None:
        profile = profile or {}
        self.cluster = Cluster([s for s in plan if s.name not in profile], log_dir, echo=False)
        self.profiled = [(s, profile[s.name]) for s in plan if s.name in profile]
        self.procs = Procs(log_dir)

    def start(self) -> None:
        self.cluster.start()
        for spec, prof in self.profiled:
            self.procs.start(
                spec.name, macb_argv("serve", *spec.args, profile=prof), dict(spec.env)
            )

    def popen(self, name: str) -> subprocess.Popen:
        return self.cluster.procs.get(name) or self.procs.procs[name]

    def stop(self) -> None:
        """The profiled services first (cProfile writes its file as the service exits,
        while the bus is still up), then the cluster, router last; all by PID."""
        self.procs.stop_all()
        self.cluster.stop()


class TimedWatch(RunWatch):
    """RunWatch over every run on the bus (`macb up --run` picks the run id), keeping the
    arrival time of every metrics and status message: a run's steady window is matched
    to CPU samples in this process's clock, start-up and the evaluator's lag are
    differences of arrivals. RunWatch decodes; what it stores for the key's source or
    service is what arrived (a message it drops leaves the stored value unchanged)."""

    def __init__(self, endpoint: str) -> None:
        super().__init__(run="*", assign=Assignment(learner="*", actors=()))  # no run's own
        self.metric_times: dict[str, list[tuple[float, dict[str, Any]]]] = {}
        self.status_times: dict[str, list[tuple[float, dict[str, Any]]]] = {}
        self.bus = Bus([endpoint])
        self.attach(self.bus)

    def _on_metrics(self, key: str, payload: bytes) -> None:
        now = time.monotonic()
        super()._on_metrics(key, payload)
        self._arrived(now, key, self.latest, self.metric_times)

    def _on_status(self, key: str, payload: bytes) -> None:
        now = time.monotonic()
        super()._on_status(key, payload)
        self._arrived(now, key, self.states, self.status_times)

    def _arrived(self, now: float, key: str, stored: dict, times: dict) -> None:
        name = key.split("/", 4)[-1]  # macb/run/RUN/{metrics,status}/NAME: NAME may hold "/"
        with self.changed:
            data, seen = stored.get(name), times.setdefault(name, [])
            if data is not None and (not seen or seen[-1][1] is not data):
                seen.append((now, data))

    def close(self) -> None:
        self.bus.close()


def exploration(config: dict[str, Any]):
    """(config, task spec, count exploration) of a run config, as a run builds them."""
    from shared.config import make_config
    from shared.envs.tasks import task_spec_for
    from shared.run.factories import build_exploration

    cfg = make_config(config)
    spec = task_spec_for(cfg)
    return cfg, spec, build_exploration(cfg, spec)


def bench_parser(
    doc: str, result: str, extra: str = "", prints: str = "markdown tables"
) -> argparse.ArgumentParser:
    """A benchmark's parser: its docstring's first paragraph (and `extra`) to say what it
    measures, and where its JSON goes (`add_out` adds the flag)."""
    return argparse.ArgumentParser(
        description=doc.split("\n\n")[0] + extra,
        epilog=f"Prints {prints}; writes --out (default benchmarks/results/{result}).",
    )


def add_out(parser: argparse.ArgumentParser, result: str) -> None:
    parser.add_argument(
        "--out", type=Path, default=RESULTS / result, help="where to write the JSON results"
    )


def progress(msg: str) -> None:
    """A progress line on stderr: stdout carries only the tables."""
    print(msg, file=sys.stderr, flush=True)


def begin_run(work: Path, what: str) -> tuple[float, float, float]:
    """A run's fresh work directory, and a progress line with the load average now, which
    the run's result keeps: on a shared machine a number means little without it."""
    work.mkdir()
    load = os.getloadavg()
    progress(f"{what} (load {load[0]:.2f}) ...")
    return load


def command(script: str, argv: list[str] | None) -> str:
    """The command line a result came from, for its JSON."""
    return " ".join([f"benchmarks/{Path(script).name}", *(argv or sys.argv[1:])])


def metric_rows(out: Path) -> list[dict[str, str]]:
    """The metric rows a `macb train --out` or `macb up --run --out` run wrote to
    out/metrics.csv (its header's names, values as text); every version writes it."""
    with open(out / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def ran_precision(out: Path) -> str | None:
    """The precision the run in `out` ran in, from its provenance.json (its latest
    start); None where it has none (a commit from before the file). A variant that asks
    for bf16 runs fp32 on a CPU without native bf16: its label alone would mislead."""
    try:
        starts = json.loads((out / "provenance.json").read_text())["starts"]
        return str(starts[-1]["learner"]["precision"])
    except (OSError, ValueError, KeyError, IndexError, TypeError):
        return None


def write_result(out: Path, result: dict[str, Any], load_before: tuple[float, ...]) -> None:
    """The JSON result, and the load average around the benchmark: on a shared machine
    a number means little without it."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"\nwrote {out}; load average before {load_before}, after {os.getloadavg()}")
