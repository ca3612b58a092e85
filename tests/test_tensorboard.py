"""TensorBoard event files from `macb train --tensorboard` and `macb export`, read back
with TensorBoard's own EventAccumulator: every metric of every row, at step = episode,
one folder per run named by experiment, arm and seed."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from cli.tensorboard import scalars
from services.api.store import Store
from tests.harness import TINY, macb, start_api

TRAIN = ["--task", "simple", "--algo", "ddpg", "--explore", "dis-macb", "--k", "32"]
TRAIN += ["--hidden", "32,32", "--batch-size", "16", "--eval-episodes", "2"]
TRAIN += ["--episodes", "8", "--eval-every", "2", "--learning-starts", "20"]
TRAIN += ["--learner-lanes", "1", "--quiet", "--cut-every", "0"]


def read_back(folder: Path) -> dict[str, list[tuple[int, float]]]:
    """tag -> [(step, value)] as TensorBoard loads the folder."""
    acc = EventAccumulator(str(folder), size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: [(s.step, s.value) for s in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def expected(rows: list[dict]) -> dict[str, list[tuple[int, float]]]:
    out: dict[str, list[tuple[int, float]]] = {}
    for row in rows:
        for tag, value in scalars(row).items():
            out.setdefault(tag, []).append((row["episode"], value))
    return out


def assert_same(got: dict, want: dict) -> None:
    assert sorted(got) == sorted(want)
    for tag, points in want.items():
        assert [s for s, _ in got[tag]] == [s for s, _ in points], tag
        # TensorBoard keeps scalars as float32
        assert [v for _, v in got[tag]] == pytest.approx([v for _, v in points], rel=1e-6), tag


def jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_macb_train_writes_every_metric_and_a_resume_does_not_repeat_steps(tmp_path):
    out, tb = tmp_path / "ddpg-run", tmp_path / "tb"
    proc = macb("train", *TRAIN, "--out", str(out), "--tensorboard", str(tb), check=True)
    assert f"TensorBoard events in {tb / 'ddpg-run'}/" in proc.stdout
    rows = jsonl(out / "metrics.jsonl")
    got = read_back(tb / "ddpg-run")
    assert_same(got, expected(rows))
    assert {"success_rate", "count1_pct", "bonus_mean", "steps_per_sec", "updates"} <= set(got)
    assert [s for s, _ in got["success_rate"]] == [2, 4, 6, 8]
    # Killed after its cut at episode 6 (its newest cut removed): the resumed life writes
    # episode 8 again, and TensorBoard shows each step once, the new values.
    sorted((out / "cuts").glob("cut-*.pt"))[-1].unlink()
    macb(
        "train",
        "--resume",
        str(out),
        "--tensorboard",
        str(tb),
        "--quiet",
        "--cut-every",
        "0",
        check=True,
    )
    resumed = jsonl(out / "metrics.jsonl")
    after = read_back(tb / "ddpg-run")
    assert [s for s, _ in after["success_rate"]] == [2, 4, 6, 8]
    assert_same(after, expected(resumed))


def test_macb_export_writes_a_folder_per_run_named_by_experiment_arm_and_seed(tmp_path):
    """An experiment of three arms x two seeds in a real API and store (its points written
    as the scheduler writes them); exported from the API and from the store file. Two
    arms whose names clean up to one folder name ("a/b c", "a_b c") each keep their
    events, in folders ending in their run ids."""
    server = start_api(tmp_path, None)  # no bus
    try:
        arms = [{"name": "Cen-MACB", "explore": "cen-macb"}, {"name": "a/b c", "explore": "none"}]
        arms.append({"name": "a_b c", "explore": "constant"})
        body = {**TINY, "seeds": [0, 1], "arms": arms, "name": "tb check"}
        exp = httpx.post(f"{server.url}/experiments", json=body).json()
        store = Store(server.settings.db_path)
        points = {}
        for i, run in enumerate(exp["runs"]):
            rows = [
                {"episode": e, "env_steps": 20 * e, "success_rate": 0.1 * i + 0.01 * e}
                | {"count1_pct": 50.0 - e, "replay_ratio": 1.0, "policy_lag": i}
                for e in (4, 8, 12)
            ]
            store.add_points(run["id"], rows)
            points[run["id"]] = rows
        store.close()
        via_api = tmp_path / "from-api"
        macb("export", exp["id"], "--api", server.url, "--tensorboard", str(via_api), check=True)
        one = tmp_path / "one-run"
        macb(
            "export",
            exp["runs"][3]["id"],
            "--api",
            server.url,
            "--tensorboard",
            str(one),
            check=True,
        )
    finally:
        server.stop()
    via_db = tmp_path / "from-db"
    db = str(server.settings.db_path)
    proc = macb(
        "export",
        exp["id"],
        "--db",
        db,
        "--tensorboard",
        str(via_db),
        "--csv",
        str(tmp_path / "csv"),
        check=True,
    )
    assert "TensorBoard: 6 run(s), 18 points" in proc.stdout
    top = f"tb_check-{exp['id']}"

    def folder(run: dict) -> str:
        if run["arm"] == "Cen-MACB":
            return f"Cen-MACB-seed{run['seed']}"
        return f"a_b_c-seed{run['seed']}-{run['id']}"  # two arms' runs share the name

    for root in (via_api, via_db):
        assert [p.name for p in root.iterdir()] == [top]
        folders = sorted(p.name for p in (root / top).iterdir())
        assert folders == sorted(folder(r) for r in exp["runs"])
        for run in exp["runs"]:
            got = read_back(root / top / folder(run))
            assert_same(got, expected(points[run["id"]]))
    run3 = exp["runs"][3]  # exported alone, in the folder the experiment's export gives it
    assert [p.name for p in (one / top).iterdir()] == [folder(run3)]
    # exporting again replaces a run's events: still one value per step
    macb("export", exp["id"], "--db", db, "--tensorboard", str(via_db), check=True)
    again = read_back(via_db / top / "Cen-MACB-seed0")
    assert [s for s, _ in again["success_rate"]] == [4, 8, 12]
    assert (tmp_path / "csv" / "metrics.csv").read_text().count("\n") == 1 + 18


def test_macb_export_refuses_what_it_cannot_find(tmp_path):
    tb = ("--tensorboard", str(tmp_path))
    proc = macb("export", "nope", "--db", str(tmp_path / "none.sqlite3"), *tb, timeout=60)
    assert proc.returncode == 2 and "no store file" in proc.stderr
    Store(tmp_path / "s.sqlite3").close()
    proc = macb("export", "nope", "--db", str(tmp_path / "s.sqlite3"), *tb, timeout=60)
    assert proc.returncode == 1 and "no run or experiment 'nope'" in proc.stderr
    proc = macb("export", "x")
    assert proc.returncode == 2 and "--tensorboard DIR and/or --csv DIR" in proc.stderr


def test_macb_export_only_reads_its_store_and_refuses_a_file_that_is_none(tmp_path):
    """`--db` reads: an older API's store is exported from a copy and left as it was
    (opening it as a store would migrate it, and that API could no longer read it); a
    file that is not a store is refused, naming it, and left alone too."""
    import contextlib
    import hashlib
    import shutil
    import sqlite3

    from tests.store_schema1 import COMMITTED

    old = tmp_path / "old.sqlite3"
    shutil.copy(COMMITTED, old)
    before = hashlib.sha256(old.read_bytes()).hexdigest()
    with contextlib.closing(sqlite3.connect(old)) as con:  # (closed: it leaves no -wal)
        exp = con.execute("SELECT id FROM experiments ORDER BY id").fetchone()[0]
    proc = macb("export", exp, "--db", str(old), "--csv", str(tmp_path / "csv"), timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "point" in proc.stdout and (tmp_path / "csv").is_dir()
    assert hashlib.sha256(old.read_bytes()).hexdigest() == before
    # Nothing beside it either (SQLite's read-only open of a WAL-mode file left a -wal
    # and a -shm: a file with no -wal beside it is copied as bytes)
    assert {p.name for p in tmp_path.iterdir()} == {"csv", "old.sqlite3"}
    other = tmp_path / "notes.sqlite3"
    with sqlite3.connect(other) as c:
        c.execute("CREATE TABLE notes (x)")
    text = tmp_path / "text.sqlite3"
    text.write_text("not a database\n")
    for bad in (other, text):
        kept = bad.read_bytes()
        proc = macb("export", "x", "--db", str(bad), "--csv", str(tmp_path / "c2"), timeout=60)
        assert proc.returncode == 2 and f"macb export: {bad}: not a" in proc.stderr, proc.stderr
        assert "Traceback" not in proc.stderr and bad.read_bytes() == kept


def test_a_store_a_running_api_writes_is_read_with_what_its_log_holds(tmp_path):
    """A store with a `-wal` beside it (an API writing it now) is read through SQLite, so
    what is committed but not yet checkpointed into the file is in the copy."""
    import shutil
    import sqlite3

    from cli.store_file import store_copy
    from tests.store_schema1 import COMMITTED

    db = tmp_path / "live.sqlite3"
    shutil.copy(COMMITTED, db)
    with store_copy(str(db)) as store:  # (bytes: no -wal yet)
        exp = store.experiments()[0]["id"]
    writer = sqlite3.connect(db)
    try:
        writer.execute("PRAGMA journal_mode=wal")
        writer.execute("PRAGMA wal_autocheckpoint=0")
        writer.execute("UPDATE experiments SET name = 'renamed' WHERE id = ?", (exp,))
        writer.commit()
        assert (tmp_path / "live.sqlite3-wal").stat().st_size > 0
        with store_copy(str(db)) as store:
            assert store.experiment(exp)["name"] == "renamed"
    finally:
        writer.close()


def test_a_store_that_changes_while_its_bytes_are_copied_is_read_again(tmp_path, monkeypatch):
    """An API that starts (and writes) while its store's bytes are copied: the copy may
    mix two states that SQLite's quick check passes, so a file whose size, time or `-wal`
    changed meanwhile is read again through SQLite."""
    import contextlib
    import shutil
    import sqlite3

    import cli.store_file as store_file
    from tests.store_schema1 import COMMITTED

    db = tmp_path / "s.sqlite3"
    shutil.copy(COMMITTED, db)
    with store_file.store_copy(str(db)) as store:
        exp = store.experiments()[0]["id"]
    copy_bytes = shutil.copyfile

    def copy_then_write(src, dst):  # the bytes read, then the API's write lands
        out = copy_bytes(src, dst)
        with contextlib.closing(sqlite3.connect(db)) as writer:
            writer.execute("UPDATE experiments SET name = 'renamed' WHERE id = ?", (exp,))
            writer.commit()
        return out

    monkeypatch.setattr(shutil, "copyfile", copy_then_write)
    with store_file.store_copy(str(db)) as store:
        assert store.experiment(exp)["name"] == "renamed"
