"""What a run actually ran on: code, machine, libraries and the learner's arithmetic.

A run's config says what was asked for; this says what happened. The two can differ:
`precision: bf16` runs fp32 on a CPU without native bf16 (shared/core/learners/precision.py),
and the same config gives different speeds and roundings on different CPUs (docs/
performance.md measured four). A result is only as trustworthy as the record of where
it came from, so every start of a run (the first, and each resume, possibly elsewhere)
adds one entry to the run's `provenance.json`; docs/reliability.md has the format.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from importlib import metadata
from pathlib import Path
from typing import Any

import torch

from shared.core.learners.precision import NATIVE_BF16_FLAGS, cpu_flags
from shared.persist.files import write_json

FILE = "provenance.json"
# Distributions whose versions change a run's numbers or its environments.
PACKAGES = ("macb", "torch", "numpy", "mpe2", "pettingzoo", "gymnasium", "eclipse-zenoh")
ROOT = Path(__file__).resolve().parents[2]  # shared/persist/ -> the checkout


class ProvenanceError(ValueError):
    """A provenance.json that is not this module's format: refused, named."""


def code(root: Path = ROOT) -> dict[str, Any]:
    """The git commit of the checkout this code runs from and whether tracked files
    differ from it; both None where it is not a git checkout (an installed copy, an
    image built without .git)."""

    def git(*argv: str) -> str | None:
        try:
            proc = subprocess.run(
                ["git", "-C", str(root), *argv], capture_output=True, text=True, timeout=10
            )
        except (OSError, subprocess.SubprocessError):
            return None
        return proc.stdout.strip() if proc.returncode == 0 else None

    top = git("rev-parse", "--show-toplevel")  # this checkout's, not an enclosing repo's
    commit = git("rev-parse", "HEAD") if top and Path(top).resolve() == root.resolve() else None
    changed = git("status", "--porcelain", "--untracked-files=no") if commit else None
    return {"commit": commit, "dirty": None if changed is None else bool(changed)}


def machine(cpuinfo: str | None = None) -> dict[str, Any]:
    """The CPU (model, logical CPUs, the native bf16 flags it reports) and the OS."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    model = next(
        (
            line.partition(":")[2].strip()
            for line in cpuinfo.splitlines()
            if line.partition(":")[0].strip() == "model name"
        ),
        platform.processor() or None,
    )
    flags = cpu_flags(cpuinfo)
    return {
        "cpu": model,
        "cpus": os.cpu_count(),
        "bf16_flags": sorted(f for f in NATIVE_BF16_FLAGS if f in flags),
        "platform": platform.platform(),
    }


def packages() -> dict[str, str | None]:
    """Python's version and the installed versions of PACKAGES (None: not installed)."""
    out: dict[str, str | None] = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def learner_record(precision_asked: str, stats: dict[str, Any]) -> dict[str, Any]:
    """The learner's arithmetic: the precision asked for and the one its products run in
    (its `stats()` say bf16 = 1 or 0; a learner without the key runs fp32), and whether
    bf16's master-weight work runs in the compiled kernel."""
    ran = "bf16" if stats.get("bf16") == 1.0 else "fp32"
    out: dict[str, Any] = {"precision_asked": precision_asked, "precision": ran}
    if ran != precision_asked:
        out["why"] = (
            f"this CPU has no native bf16 (none of {', '.join(NATIVE_BF16_FLAGS)} in its flags)"
            if precision_asked == "bf16"
            else "the learner reports another precision"
        )
    if "fused" in stats:
        out["fused_kernel"] = stats["fused"] == 1.0
    return out


def entry(precision_asked: str, learner_stats: dict[str, Any], role: str) -> dict[str, Any]:
    """One start of a run: when, by whom (`role`: "trainer", "learner"), and on what."""
    return {
        "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "role": role,
        "code": code(),
        "machine": machine(),
        "packages": packages(),
        "torch_threads": torch.get_num_threads(),
        "learner": learner_record(precision_asked, learner_stats),
    }


def read(path: Path) -> list[dict[str, Any]]:
    """The starts recorded in `path` ([] when it does not exist); a file that is not a
    provenance record is refused, naming it."""
    if not path.exists():
        return []
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ProvenanceError(f"{path}: not a provenance record ({err})") from err
    if not isinstance(data, dict) or not isinstance(data.get("starts"), list):
        raise ProvenanceError(f"{path}: not a provenance record (no 'starts' list)")
    if not all(isinstance(s, dict) for s in data["starts"]):
        raise ProvenanceError(f"{path}: not a provenance record (a start is not an object)")
    return data["starts"]


def append(path: Path, start: dict[str, Any]) -> list[dict[str, Any]]:
    """Add one start to `path` (created if missing), replaced atomically; returns all."""
    starts = [*read(path), start]
    write_json(path, {"starts": starts})
    return starts


def reported(run: dict[str, Any]) -> dict[str, Any] | None:
    """The learner's latest start as a cluster run's record holds it (the API's run,
    `live.provenance`), or None where the learner reported none."""
    start = (run.get("live") or {}).get("provenance")
    return start if isinstance(start, dict) else None


def write(path: Path, starts: list[dict[str, Any]]) -> None:
    """`path` holding exactly these starts (what a cluster run's learners reported)."""
    write_json(path, {"starts": starts})
