"""A write-ahead log of batches, on the one record log (`records.py`).

Two services keep one. The counter logs the SimHash keys of every batch it takes, the
learner every batch of transitions it takes (the rows as byte columns), so that either,
killed with SIGKILL, rebuilds what it acknowledged. For the counter: it appends a
record for every batch it takes (consecutive batches of one actor taken together share
one record; after hashing, before it increments its tables and before it acknowledges
the batch), so that a counter killed with SIGKILL can rebuild everything it
acknowledged from the last snapshot plus this log.

A record's body (after the record log's frame)::

    <H   actor id length, then the actor id (UTF-8)
    <qIH seq (first transition number), n (rows), number of tables
    per table: <I key width w, then n * w key bytes (row-major uint8)

Records are flushed to the OS after each append (no fsync: the log survives the
process dying, which is what it is for, not the machine dying); one append may carry
several records in one write, as the counter logs a whole burst of batches at once. A
torn or corrupt record, or a body that does not parse, ends the log: it was never
acknowledged, so the actor resends it. `WriteAheadLog.open` cuts such a tail off.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.persist import records
from shared.persist.records import RecordLog, RecordLogError

MAGIC = b"MACBWAL1"
WHAT = "write-ahead log"
_ACTOR = struct.Struct("<H")
_BATCH = struct.Struct("<qIH")
_WIDTH = struct.Struct("<I")


@dataclass
class WalRecord:
    actor: str
    seq: int
    n: int
    keys: list[np.ndarray]  # per table: (n, key width) uint8


def pack_body(actor: str, seq: int, keys: list[np.ndarray], n: int) -> bytes:
    """One record's body."""
    name = actor.encode()
    parts = [_ACTOR.pack(len(name)), name, _BATCH.pack(seq, n, len(keys))]
    for k in keys:
        k = np.ascontiguousarray(k, dtype=np.uint8)
        if k.ndim != 2 or k.shape[0] != n:
            raise ValueError(f"keys must be ({n}, width) uint8, got {k.shape}")
        parts.append(_WIDTH.pack(k.shape[1]))
        parts.append(k.tobytes())
    return b"".join(parts)


def _unpack_body(body: bytes | memoryview) -> WalRecord:
    (alen,) = _ACTOR.unpack_from(body, 0)
    pos = _ACTOR.size
    actor = bytes(body[pos : pos + alen]).decode()
    pos += alen
    seq, n, ntables = _BATCH.unpack_from(body, pos)
    pos += _BATCH.size
    keys = []
    for _ in range(ntables):
        (width,) = _WIDTH.unpack_from(body, pos)
        pos += _WIDTH.size
        size = n * width
        if pos + size > len(body):
            raise ValueError("record keys run past its end")
        keys.append(np.frombuffer(body, np.uint8, count=size, offset=pos).reshape(n, width))
        pos += size
    if pos != len(body):
        raise ValueError("record has trailing bytes")
    return WalRecord(actor, seq, n, keys)


def read_wal(path: Path) -> tuple[list[WalRecord], int, bool]:
    """Parse a log: (records, length of the valid prefix in bytes, whether a tail was cut).

    A missing or empty file is an empty log. A file without the magic header is refused
    (ValueError naming it): it is not ours, and guessing would corrupt counts.
    """
    try:
        data, starts, valid, torn = records.read(Path(path), MAGIC, WHAT)
    except RecordLogError as err:
        raise ValueError(str(err)) from None
    out: list[WalRecord] = []
    for start in starts:
        try:
            out.append(_unpack_body(records.body(data, start)))
        except (ValueError, struct.error, UnicodeDecodeError):
            return out, start, True  # a body that does not parse ends the log
    return out, valid, torn


class WriteAheadLog:
    """Append-only log of taken batches; `truncate` empties it after a snapshot."""

    def __init__(self, path: Path, log: RecordLog | None = None) -> None:
        self.path = Path(path)
        self._log = log if log is not None else RecordLog(self.path, MAGIC)

    @property
    def records(self) -> int:
        """Records appended since the last truncate."""
        return self._log.records

    @property
    def bytes(self) -> int:
        return self._log.bytes

    @classmethod
    def open(cls, path: Path) -> tuple[WriteAheadLog, list[WalRecord]]:
        """Read what an earlier process logged, cut a torn tail, and open for appending."""
        found, valid, _ = read_wal(path)
        return cls(path, RecordLog.resume(path, MAGIC, valid, len(found))), found

    def append(self, actor: str, seq: int, n: int, keys: list[np.ndarray]) -> None:
        """Write one record and hand it to the OS before returning."""
        self.append_many([(actor, seq, n, keys)])

    def append_many(self, batches: list[tuple[str, int, int, list[np.ndarray]]]) -> None:
        """Write several records (actor, seq, n, keys) with one write and one flush.

        The counter logs everything it takes in one burst this way: one system call
        instead of one per batch, and still all on the OS's side before any of them
        is acknowledged.
        """
        self._log.append(pack_body(actor, seq, keys, n) for actor, seq, n, keys in batches)

    def sync(self) -> None:
        """fsync: what was appended survives the machine too, not only the process."""
        self._log.sync()

    def truncate(self) -> None:
        """Drop every record (they are in a snapshot now); keep the header."""
        self._log.truncate()

    def close(self) -> None:
        self._log.close()
