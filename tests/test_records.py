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
