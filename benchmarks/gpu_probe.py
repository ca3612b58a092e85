"""What figure 8's run groups would do on a GPU, measured in a short window on one.

Run on a machine with a CUDA torch, no network needed (it imports torch, numpy and
the repository's learners only, none of its other dependencies):

    PYTHONPATH=. python3 benchmarks/gpu_probe.py            # for a 10-minute GPU window
    PYTHONPATH=. python3 benchmarks/gpu_probe.py --device cpu --quick   # a smoke run

For a group of R runs of figure 8's sparse arms (speaker_listener, Cen-MADDPG, 400-300,
profile thesis: one minibatch of 100 rows per agent), per R (6 and 12) and precision:

* `update_ms`: `GroupMADDPG.update` as the trainer calls it, from numpy batches (the
  inputs staged and sent each update), timed over many updates with one wait at the end;
* `update_device_inputs_ms`: the same on batches already on the device;
* `graph_ms`: that update captured once as a CUDA graph and replayed (CUDA only; the
  error instead when it cannot be captured);
* `syncs_per_update`: host waits torch counts in one update (sync debug mode `warn`),
  and `sync_free`: whether an update runs under mode `error` (CUDA only);
* `ops_per_update`: torch ops dispatched by one update; `kernels_per_update`: device
  kernels launched by one (CUDA only, from torch's profiler);
* `act_ms`: `act` for one observation per run, its actions read back (one wait).

Without a usable device it says it skipped, writes that, and exits 0. It writes one JSON
(`--out`, default benchmarks/results/gpu_probe.json).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils._python_dispatch import TorchDispatchMode

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from shared.core.learners.base import AgentDims, LearnerSpec  # noqa: E402
from shared.core.learners.group import GroupMADDPG, capture_update  # noqa: E402

# speaker_listener in profile thesis (observations padded to 11; tests/test_device.py
# checks these against the task's spec): the speaker's 3 in [0, 1], the listener's 2.
AGENTS = [
    AgentDims(11, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
    AgentDims(11, (-1.0, -1.0), (1.0, 1.0)),
]
BATCH = 100


def group(runs: int, precision: str, device: str) -> GroupMADDPG:
    specs = [LearnerSpec(algo="cen-maddpg", seed=s, same_init=True) for s in range(runs)]
    return GroupMADDPG(AGENTS, specs, precision=precision, device=device)


def batches(rng: np.random.Generator, runs: int, count: int) -> list[tuple[np.ndarray, ...]]:
    """`count` batches of every run, one minibatch per agent (R, N, B, ...)."""
    n, f = len(AGENTS), np.float32
    obs_dim, act_dim = sum(a.obs_dim for a in AGENTS), sum(a.act_dim for a in AGENTS)
    lead = (runs, n, BATCH)
    return [
        (
            rng.standard_normal((*lead, obs_dim)).astype(f),
            rng.uniform(-1, 1, (*lead, act_dim)).astype(f),
            rng.standard_normal((*lead, n)).astype(f),
            rng.standard_normal((*lead, obs_dim)).astype(f),
            (rng.random(lead) < 0.05).astype(f),
        )
        for _ in range(count)
    ]


def wait(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def timed(fn: Any, items: list[Any], device: str) -> float:
    """Milliseconds per call of fn over items, one wait at the end."""
    wait(device)
    t0 = time.perf_counter()
    for item in items:
        fn(item)
    wait(device)
    return 1e3 * (time.perf_counter() - t0) / len(items)


class OpCount(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.ops = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001
        self.ops += 1
        return func(*args, **(kwargs or {}))


def syncs(g: GroupMADDPG, batch: tuple[np.ndarray, ...]) -> dict[str, Any]:
    """Host waits in one update: counted in mode `warn`, then whether mode `error` passes."""
    out: dict[str, Any] = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            g.update(*batch)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    found = [str(w.message) for w in caught if "synchroniz" in str(w.message).lower()]
    out["syncs_per_update"] = len(found)
    out["first_sync"] = found[0].splitlines()[0] if found else None
    torch.cuda.set_sync_debug_mode("error")
    try:
        g.update(*batch)
        out["sync_free"] = True
    except RuntimeError as err:
        out["sync_free"] = False
        out["sync_error"] = str(err).splitlines()[0]
    finally:
        torch.cuda.set_sync_debug_mode("default")
    return out


def kernels(g: GroupMADDPG, batch: tuple[torch.Tensor, ...]) -> int | None:
    """Device kernels one update launches (torch's profiler), or None when it cannot say."""
    from torch.profiler import ProfilerActivity, profile

    try:
        with profile(activities=[ProfilerActivity.CUDA]) as prof:
            g.update(*batch)
            torch.cuda.synchronize()
    except Exception:  # a profiler without CUPTI: the count is not known
        return None
    return sum(1 for e in prof.events() if e.device_type.name == "CUDA")


def graph_ms(g: GroupMADDPG, batch: tuple[torch.Tensor, ...], replays: int) -> dict[str, Any]:
    """The update on fixed device inputs captured as one CUDA graph, replayed."""
    try:
        graph = capture_update(g, batch)
        ms = timed(lambda _: graph.replay(), list(range(replays)), "cuda")
        return {"graph_ms": ms}
    except Exception as err:  # what stops a capture is what the probe is for
        return {"graph_ms": None, "graph_error": f"{type(err).__name__}: {err}".splitlines()[0]}


def measure(runs: int, precision: str, device: str, updates: int) -> dict[str, Any]:
    rng = np.random.default_rng(runs)
    g = group(runs, precision, device)
    warm = batches(rng, runs, 3)
    for b in warm:
        g.update(*b)
    row: dict[str, Any] = {"runs": runs, "precision": g.precision, "rows_per_agent": BATCH}
    host = batches(rng, runs, updates)
    row["update_ms"] = timed(lambda b: g.update(*b), host, device)
    on_device = [tuple(g.tensors(*b)) for b in host]
    row["update_device_inputs_ms"] = timed(lambda b: g.update(*b), on_device, device)
    counter = OpCount()
    with counter:
        g.update(*host[0])
    row["ops_per_update"] = counter.ops
    obs = [rng.standard_normal((runs, 1, g.joint_obs)).astype(np.float32) for _ in range(updates)]
    row["act_ms"] = timed(g.act, obs, device)
    if device.startswith("cuda"):
        row.update(syncs(g, host[0]))
        row["kernels_per_update"] = kernels(g, on_device[0])
        row.update(graph_ms(g, on_device[0], updates))
    else:
        row.update(syncs_per_update=None, kernels_per_update=None, graph_ms=None)
    row["run_updates_per_s"] = 1e3 * runs / row["update_ms"]
    return row


def usable(device: str) -> str | None:
    """Why `device` cannot be probed here, or None."""
    kind = torch.device(device).type
    if kind == "cpu":
        return None
    if kind != "cuda":
        return f"device {device}: the probe measures CUDA (or the CPU, --device cpu)"
    if not torch.cuda.is_available():
        return f"no CUDA device (torch {torch.__version__}, built for CUDA {torch.version.cuda})"
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda", help="cuda (default), cuda:N or cpu")
    ap.add_argument("--runs", type=int, nargs="+", default=[6, 12], help="group sizes")
    ap.add_argument("--precision", nargs="+", default=["fp32"], choices=("fp32", "bf16"))
    ap.add_argument("--updates", type=int, default=200, help="timed updates per measure")
    ap.add_argument("--quick", action="store_true", help="a smoke run: 2 runs, 5 updates")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "gpu_probe.json"))
    args = ap.parse_args(argv)
    if args.quick:
        args.runs, args.updates = [2], 5
    result: dict[str, Any] = {
        "device": args.device,
        "torch": torch.__version__,
        "python": platform.python_version(),
        "machine": platform.processor() or platform.machine(),
    }
    if torch.device(args.device).type == "cpu":
        torch.set_num_threads(1)  # as a group's update in the trainer (threads: 1)
    why = usable(args.device)
    if why is not None:
        print(f"gpu_probe: skipped: {why}")
        result["skipped"] = why
    else:
        if args.device.startswith("cuda"):
            result["gpu"] = torch.cuda.get_device_name(torch.device(args.device))
        rows = []
        for runs in args.runs:
            for precision in args.precision:
                print(f"measuring {runs} runs, {precision}", file=sys.stderr)
                rows.append(measure(runs, precision, args.device, args.updates))
        result["rows"] = rows
        cols = ["runs", "precision", "update_ms", "update_device_inputs_ms", "graph_ms",
                "syncs_per_update", "kernels_per_update", "ops_per_update", "act_ms"]  # fmt: skip
        print("| " + " | ".join(cols) + " |")
        print("|" + "---|" * len(cols))
        for row in rows:
            cells = [f"{v:.3g}" if isinstance(v, float) else str(v) for v in map(row.get, cols)]
            print("| " + " | ".join(cells) + " |")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
