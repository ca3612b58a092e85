"""The API's store (services/api/store.py): what survives a restart of the API, the CSV
columns, a newer schema refused, and schema-1 and schema-3 files migrated."""

from __future__ import annotations

import contextlib
import shutil
import sqlite3

import httpx
import pytest

from services.api import views
from services.api.store import CSV_FIELDS, SCHEMA_VERSION, Store, StoreError
from tests.harness import TINY, post, row, start_api


def test_csv_columns_are_the_trainers_then_the_services():
    from cli.trainer import METRIC_FIELDS
    from shared.metrics import SERVICE_FIELDS

    assert CSV_FIELDS == METRIC_FIELDS + SERVICE_FIELDS


def test_everything_survives_a_restart_of_the_api(router, tmp_path):
    first = start_api(tmp_path, router)
    with httpx.Client(base_url=first.url) as c:
        exp = post(c, {**TINY, "seeds": [3, 4], "grid": {"k": [32, 64]}}).json()
        c.post(f"/runs/{exp['runs'][1]['id']}/stop")
        store = Store(first.settings.db_path)
        store.add_points(exp["runs"][0]["id"], [row(4), row(8)])
        store.close()
        before = c.get(f"/experiments/{exp['id']}").json()
        metrics = c.get(f"/runs/{exp['runs'][0]['id']}/metrics").json()
    first.stop()
    second = start_api(tmp_path, router)
    try:
        with httpx.Client(base_url=second.url) as c:
            after = c.get(f"/experiments/{exp['id']}").json()
            strip = lambda e: [{**r, "reason": None} for r in e["runs"]]  # noqa: E731
            assert strip(after) == strip(before)
            assert c.get(f"/runs/{exp['runs'][0]['id']}/metrics").json() == metrics
            assert after["runs"][1]["status"] == "stopped"
    finally:
        second.stop()


def test_a_newer_store_schema_is_refused(tmp_path):
    path = tmp_path / "s.sqlite3"
    Store(path).close()
    import sqlite3

    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE schema_version SET version = ?", (SCHEMA_VERSION + 1,))
    with pytest.raises(StoreError, match="schema"):
        Store(path)


def _columns(path) -> list[str]:
    with contextlib.closing(sqlite3.connect(path)) as conn:
        return [r[1] for r in conn.execute("PRAGMA table_info(runs)")]


def _schema1_files(tmp_path) -> list:
    """The committed schema-1 file, and one written now by the schema-1 code from git."""
    from tests.store_schema1 import COMMITTED, load_module, schema1_source, write_schema1_store

    files = [shutil.copy(COMMITTED, tmp_path / "committed.sqlite3")]
    source = schema1_source()
    if source is not None:
        fresh = tmp_path / "fresh.sqlite3"
        write_schema1_store(load_module(source, tmp_path), fresh)
        files.append(fresh)
    return files


def test_a_schema_1_store_is_migrated_and_its_runs_get_arm_names(tmp_path):
    files = _schema1_files(tmp_path)
    for path in files:
        with contextlib.closing(sqlite3.connect(path)) as conn:
            assert conn.execute("SELECT version FROM schema_version").fetchall() == [(1,)]
        assert "arm" not in _columns(path), "written by the old code"
        store = Store(path)
        try:
            with contextlib.closing(sqlite3.connect(path)) as conn:
                assert conn.execute("SELECT version FROM schema_version").fetchall() == [
                    (SCHEMA_VERSION,)
                ]
            assert SCHEMA_VERSION == 4 and {"arm", "attempts", "seq_base"} <= set(_columns(path))
            assert {(r["attempts"], r["seq_base"]) for r in store.runs_of(["xgrid"])["xgrid"]} == {
                (1, 0)
            }
            assert store.point_stats(["xgrid-3"]) == {"xgrid-3": (2, 2, 8)}
            runs = store.runs_of(["xgrid", "xplain"])
            assert [r["arm"] for r in runs["xgrid"]] == ["beta=0.2"] * 2 + ["beta=0.8"] * 2
            assert [r["arm"] for r in runs["xplain"]] == ["cen-maddpg + cen-macb"]
            assert runs["xgrid"][1]["point"] == {"beta": 0.2}, "the rest is kept"
            assert [p["success_rate"] for p in store.points("xgrid-3")] == pytest.approx([0.3, 0.6])
            data = views.curves(store, "xgrid", ["success_rate"])
            low, high = data["metrics"]["success_rate"]
            assert (low["name"], low["seeds"], low["episode"]) == ("beta=0.2", [0, 1], [4, 8])
            assert low["mean"] == pytest.approx([0.05, 0.1])
            assert high["mean"] == pytest.approx([0.25, 0.5])
            public = views.load_experiments(store, [store.experiment("xgrid")])[0]
            assert public["arms"] is None and public["runs"][0]["arm"] == "beta=0.2"
            # The migrated file takes new experiments with arms.
            store.create_experiment(
                "xnew",
                "new",
                {},
                [{"id": "xnew-0", "seed": 0, "arm": "a", "point": {}, "config": {}, "actors": 1}],
            )
        finally:
            store.close()
        again = Store(path)  # opening a migrated file again changes nothing
        try:
            assert again.run("xnew-0")["arm"] == "a"
            assert again.run("xgrid-0")["arm"] == "beta=0.2"
        finally:
            again.close()
    print(f"migrated {len(files)} schema-1 file(s)")


def test_a_schema_3_store_is_migrated_and_a_retry_there_numbers_its_points_on(tmp_path):
    """A schema-3 file (runs without `seq_base`: the file as schema 3 wrote it) gets the
    column at 0, so its points keep their seqs; a retry then numbers the new attempt's
    points on from the last one."""
    path = tmp_path / "s3.sqlite3"
    store = Store(path)
    run = {"id": "x-0", "seed": 0, "point": {}, "config": TINY, "actors": 1}
    store.create_experiment("x", "x", {"config": TINY}, [run])
    store.add_points("x-0", [row(4), row(8)])
    store.close()
    with contextlib.closing(sqlite3.connect(path)) as conn, conn:
        conn.execute("ALTER TABLE runs DROP COLUMN seq_base")
        conn.execute("UPDATE schema_version SET version = 3")
    assert "seq_base" not in _columns(path)
    store = Store(path)
    try:
        with contextlib.closing(sqlite3.connect(path)) as conn:
            assert conn.execute("SELECT version FROM schema_version").fetchall() == [(4,)]
        assert store.run("x-0")["seq_base"] == 0
        assert [(p["seq"], p["episode"]) for p in store.points("x-0")] == [(1, 4), (2, 8)]
        assert store.point_stats(["x-0"]) == {"x-0": (2, 2, 8)}
        store.finish("x-0", "failed", "boom")
        assert [r["id"] for r in store.retry_runs("x")] == ["x-0"]
        assert store.point_stats(["x-0"]) == {"x-0": (0, 0, 0)}
        assert store.add_points("x-0", [row(4)]) == 1
        assert [(p["seq"], p["episode"]) for p in store.points("x-0")] == [(3, 4)]
        assert store.point_stats(["x-0"]) == {"x-0": (1, 3, 4)}
    finally:
        store.close()


def test_the_point_stats_of_more_runs_than_sqlite_binds_at_once(tmp_path):
    """A page of experiments may hold more runs than SQLite binds variables in one
    query (32,766; 999 before 3.32): the stats are read in slices. Here the store's
    connection binds at most 999, and 2,000 runs are asked for."""
    store = Store(tmp_path / "many.sqlite3")
    try:
        runs = [
            {"id": f"x-{i}", "seed": i, "point": {}, "config": TINY, "actors": 1}
            for i in range(2000)
        ]
        store.create_experiment("x", "x", {"config": TINY}, runs)
        store.add_points("x-7", [row(4), row(8)])
        store.add_points("x-1999", [row(4)])
        store.db.conn().setlimit(sqlite3.SQLITE_LIMIT_VARIABLE_NUMBER, 999)
        stats = store.point_stats([r["id"] for r in runs])
        assert len(stats) == 2000 and stats["x-7"] == (2, 2, 8) and stats["x-1999"] == (1, 1, 4)
        assert {v for k, v in stats.items() if k not in ("x-7", "x-1999")} == {(0, 0, 0)}
    finally:
        store.close()
