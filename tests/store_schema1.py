"""A store file written by the schema-1 API (before runs carried an arm), for the
migration test.

The schema-1 `services/api/store.py` is read from git at the last commit that had it;
`write_schema1_store` fills a file with it the way that API did (a grid experiment
with points, a plain one). `tests/data/api-store-schema1.sqlite3` is such a file,
committed so the test needs no git history; `python -m tests.store_schema1` rewrites it.
"""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
SCHEMA1_COMMIT = "b02fcea6f568fcd5c2a9ca4af8372ce2f4a5ca54"  # store.py last at schema 1
COMMITTED = ROOT / "tests" / "data" / "api-store-schema1.sqlite3"

BASE = {"task": "speaker_listener", "algo": "cen-maddpg", "explore": "cen-macb", "k": 64}


def schema1_source() -> str | None:
    """The schema-1 store module's source, or None without that git history."""
    if shutil.which("git") is None:
        return None
    proc = subprocess.run(
        ["git", "-C", str(ROOT), "show", f"{SCHEMA1_COMMIT}:services/api/store.py"],
        capture_output=True,
        text=True,
    )
    return proc.stdout if proc.returncode == 0 else None


def load_module(source: str, where: Path) -> ModuleType:
    """Import a store module from its source (its imports are absolute: shared.metrics)."""
    path = where / "store_schema1_module.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("store_schema1_module", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def row(episode: int, success: float) -> dict[str, Any]:
    return {"episode": episode, "env_steps": 20 * episode, "success_rate": success}


def write_schema1_store(module: ModuleType, path: Path) -> None:
    """What a schema-1 API stored: runs with their grid point, and their points."""
    assert module.SCHEMA_VERSION == 1
    store = module.Store(path)
    grid_runs = [
        {
            "id": f"xgrid-{i}",
            "seed": seed,
            "point": {"beta": beta},
            "config": {**BASE, "beta": beta, "seed": seed},
            "actors": 1,
        }
        for i, (beta, seed) in enumerate((b, s) for b in (0.2, 0.8) for s in (0, 1))
    ]
    store.create_experiment(
        "xgrid",
        "old grid",
        {"config": BASE, "seeds": [0, 1], "grid": {"beta": [0.2, 0.8]}, "actors": 1},
        grid_runs,
    )
    for i, run in enumerate(grid_runs):
        store.add_points(run["id"], [row(4, 0.1 * i), row(8, 0.2 * i)])
    plain = {"id": "xplain-0", "seed": 3, "point": {}, "config": {**BASE, "seed": 3}, "actors": 1}
    store.create_experiment(
        "xplain", "old plain", {"config": BASE, "seeds": [3], "grid": None, "actors": 1}, [plain]
    )
    store.add_points("xplain-0", [row(4, 1.0)])
    conn = store._conn()
    conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")  # everything in the one file
    store.close()


if __name__ == "__main__":
    source = schema1_source()
    if source is None:
        sys.exit(f"commit {SCHEMA1_COMMIT} is not in this repository's history")
    COMMITTED.parent.mkdir(parents=True, exist_ok=True)
    COMMITTED.unlink(missing_ok=True)
    tmp = COMMITTED.parent / "_schema1"
    tmp.mkdir(exist_ok=True)
    try:
        write_schema1_store(load_module(source, tmp), COMMITTED)
    finally:
        shutil.rmtree(tmp)
    for suffix in ("-wal", "-shm"):
        Path(f"{COMMITTED}{suffix}").unlink(missing_ok=True)
    print(f"wrote {COMMITTED} ({COMMITTED.stat().st_size} bytes)")
