"""The one record log (shared/persist/records.py) and the replay log on it: torn tails
cut, corrupt records end the log, rows past a cut dropped, foreign files refused by name."""

from __future__ import annotations

import numpy as np
import pytest

from shared.persist import records
from shared.persist.cuts import CutError, ReplayLog
from shared.persist.records import RecordLog, RecordLogError

MAGIC = b"TESTLOG1"
WIDTH = {"obs": 3, "act": 2, "rew": 1, "next_obs": 3, "done": 1}


def rows(first: int, n: int) -> dict[str, np.ndarray]:
    """Rows whose every value says which row it is: row r holds r (+ a field offset)."""
    r = np.arange(first, first + n, dtype=np.float32)
    return {
        name: (r[:, None] + 0.25 * j).repeat(w, 1).squeeze(1) if w == 1 else
        (r[:, None] + 0.25 * j).repeat(w, 1)
        for j, (name, w) in enumerate(WIDTH.items())
    }  # fmt: skip


def test_records_come_back_and_a_torn_or_corrupt_tail_ends_the_log(tmp_path):
    path = tmp_path / "a.log"
    log = RecordLog(path, MAGIC)
    log.append([b"one", b"", b"three"])
    log.close()
    data, starts, valid, torn = records.read(path, MAGIC, "test log")
    assert [bytes(records.body(data, s)) for s in starts] == [b"one", b"", b"three"]
    assert valid == path.stat().st_size and not torn
    with open(path, "ab") as f:
        f.write(b"\x40\x00\x00\x00\x01")  # a kill in the middle of a frame
    log, _, starts = RecordLog.open(path, MAGIC, "test log")
    assert len(starts) == 3 and path.stat().st_size == valid and log.records == 3
    log.append([b"four"])
    log.close()
    raw = bytearray(path.read_bytes())
    raw[-1] ^= 0xFF  # a flipped bit in the last body: its CRC refuses it
    path.write_bytes(bytes(raw))
    data, starts, _, torn = records.read(path, MAGIC, "test log")
    assert [bytes(records.body(data, s)) for s in starts] == [b"one", b"", b"three"] and torn


def test_a_file_of_another_kind_is_refused_naming_it(tmp_path):
    path = tmp_path / "x.log"
    path.write_bytes(b"MACBWAL1" + b"\x00" * 16)
    with pytest.raises(RecordLogError, match="x.log: not a MACB test log"):
        records.read(path, MAGIC, "test log")
    with pytest.raises(CutError, match="x.log: not a MACB replay log"):
        log = ReplayLog(tmp_path)
        log.path = path
        log.read(1, WIDTH, tmp_path)


def test_the_replay_log_gives_its_rows_and_drops_those_past_a_cut(tmp_path):
    log = ReplayLog(tmp_path)
    log.append(rows(0, 10), 0, WIDTH)
    log.append(rows(10, 15), 10, WIDTH)
    back = log.read(25, WIDTH, tmp_path)
    for name, want in rows(0, 25).items():
        assert np.array_equal(back[name], want), name
    assert back["rew"].shape == (25,) and back["obs"].shape == (25, 3)
    with pytest.raises(CutError, match="needs 26 replay rows.*holds 25"):
        log.read(26, WIDTH, tmp_path)
    # A resume from a cut at row 10 (the rows after it were appended by a run killed
    # before its cut): the next cut's rows replace them.
    again = ReplayLog(tmp_path)
    again.append(rows(100, 5), 10, WIDTH)
    back = ReplayLog(tmp_path).read(15, WIDTH, tmp_path)
    assert np.array_equal(back["obs"][:10], rows(0, 10)["obs"])
    assert np.array_equal(back["obs"][10:], rows(100, 5)["obs"])
    with pytest.raises(CutError, match="holds 15"):
        ReplayLog(tmp_path).read(16, WIDTH, tmp_path)


def test_a_cut_inside_a_record_keeps_the_rows_before_it(tmp_path):
    log = ReplayLog(tmp_path)
    log.append(rows(0, 20), 0, WIDTH)
    again = ReplayLog(tmp_path)
    again.append(rows(50, 4), 7, WIDTH)  # a cut at row 7, inside the first record
    back = ReplayLog(tmp_path).read(11, WIDTH, tmp_path)
    assert np.array_equal(back["act"][:7], rows(0, 7)["act"])
    assert np.array_equal(back["act"][7:], rows(50, 4)["act"])


def test_a_replay_record_of_other_fields_is_refused_naming_the_file(tmp_path):
    ReplayLog(tmp_path).append(rows(0, 4), 0, WIDTH)
    other = {**WIDTH, "obs": 4}
    with pytest.raises(CutError, match="replay.log: rows of"):
        ReplayLog(tmp_path).read(4, other, tmp_path)


def test_rows_go_in_records_of_bounded_size_and_an_oversized_record_is_refused(
    tmp_path, monkeypatch
):
    from shared.persist import cuts

    monkeypatch.setattr(cuts, "RECORD_BYTES", 4 * 10 * 7)  # 7 rows of 10 values a record
    log = ReplayLog(tmp_path)
    log.append(rows(0, 30), 0, WIDTH)
    _, starts, _, _ = records.read(tmp_path / "replay.log", b"MACBRPL1", "replay log")
    assert len(starts) == 5  # 7 + 7 + 7 + 7 + 2 rows
    back = ReplayLog(tmp_path).read(30, WIDTH, tmp_path)
    assert np.array_equal(back["next_obs"], rows(0, 30)["next_obs"])
    monkeypatch.setattr(records, "MAX_RECORD", 16)
    big = RecordLog(tmp_path / "big.log", MAGIC)
    with pytest.raises(ValueError, match="a record over 16 bytes"):
        big.append([b"x" * 17])
    big.close()


def test_columnar_rows_of_before_are_read_as_they_are_and_converted_at_the_next_cut(tmp_path):
    for name, values in rows(0, 12).items():
        np.ascontiguousarray(values, np.float32).tofile(tmp_path / f"replay.{name}.f32")
    before = sorted(p.name for p in tmp_path.iterdir())
    back = ReplayLog(tmp_path).read(10, WIDTH, tmp_path)  # a resume from a cut at row 10
    assert np.array_equal(back["obs"], rows(0, 10)["obs"])
    assert sorted(p.name for p in tmp_path.iterdir()) == before, "reading changes nothing"
    log = ReplayLog(tmp_path)
    log.append(rows(40, 3), 10, WIDTH)  # the next cut: rows 10.. as the resumed run has them
    assert sorted(p.name for p in tmp_path.iterdir()) == ["replay.log"]
    back = ReplayLog(tmp_path).read(13, WIDTH, tmp_path)
    assert np.array_equal(back["done"], np.concatenate([rows(0, 10)["done"], rows(40, 3)["done"]]))
    # a conversion killed after replay.log was in place, before the columns were removed
    (tmp_path / "replay.obs.f32").write_bytes(b"\0" * 48)
    ReplayLog(tmp_path).append(rows(50, 1), 13, WIDTH)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["replay.log"]


def test_checkpoints_of_format_1_still_load_and_other_formats_or_kinds_are_refused(tmp_path):
    """Format 2 adds `kind`; a format-1 file (no kind, the service's bare sampler state
    as its rng, a cut's tables as a list) reads as before; an earlier version refuses a
    format-2 file by its format rather than misreading it."""
    import json

    import torch

    from shared.config import make_config
    from shared.core.counting import CountTable
    from shared.persist import checkpoint

    config = make_config({"task": "simple", "algo": "ddpg"}).model_dump(mode="json")
    table = CountTable(4)
    table.increment(np.arange(8, dtype=np.uint8).reshape(2, 4))
    path = tmp_path / "c.pt"
    checkpoint.save(path, "cut", config, {"w": torch.ones(2)}, {"rows": 2},
                    rng={"sampler": {"state": 1}}, tables=[table], episode=3)  # fmt: skip
    raw = torch.load(path, weights_only=True)
    assert raw["format"] == 2 and raw["kind"] == "cut" and set(raw["tables"]) == {"table0"}
    assert checkpoint.load(path, "cut", config)["rng"] == {"sampler": {"state": 1}}
    with pytest.raises(CutError, match="a cut checkpoint, not a service one"):
        checkpoint.load(path, "service", config)

    old = {k: v for k, v in raw.items() if k != "kind"}
    old |= {"format": 1, "rng": json.dumps({"state": 1}), "tables": [raw["tables"]["table0"]]}
    torch.save(old, path)
    state = checkpoint.load(path, "service", config)
    assert state["rng"] == {"sampler": {"state": 1}}
    tables = [CountTable(4)]
    checkpoint.load_tables(tables, state["tables"], path)
    assert tables[0].total == 2

    torch.save({**old, "format": 3}, path)
    with pytest.raises(CutError, match="c.pt: cut format 3, this version reads 2"):
        checkpoint.load(path, "cut", config)
    torch.save({k: v for k, v in old.items() if k != "learner"}, path)
    with pytest.raises(checkpoint.UnreadableCheckpoint, match="no learner or counters"):
        checkpoint.load(path, "cut", config)
