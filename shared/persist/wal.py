"""A write-ahead log of batches: one append-only file of struct-packed records.

Two services keep one. The counter logs the SimHash keys of every batch it takes, the
learner every batch of transitions it takes (the rows as byte columns), so that either,
killed with SIGKILL, rebuilds what it acknowledged. For the counter: it appends a
record for every batch it takes (consecutive batches of one
actor taken together share one record; after hashing, before it increments its
tables and before it acknowledges the batch), so that a counter
killed with SIGKILL can rebuild everything it acknowledged from the last snapshot
plus this log. No msgpack, no pickle: the format is fixed binary.

File layout::

    header  MAGIC (8 bytes)
    record  <II  body length, CRC-32 of the body
            body:
              <H   actor id length, then the actor id (UTF-8)
              <qIH seq (first transition number), n (rows), number of tables
              per table: <I key width w, then n * w key bytes (row-major uint8)

Records are flushed to the OS after each append (no fsync: the log survives the
process dying, which is what it is for, not the machine dying); one append may carry
several records in one write, as the counter logs a whole burst of batches at once. A
record cut short by a kill, or one whose CRC does not match, ends the log: it was
never acknowledged, so the actor resends it. `WriteAheadLog.open` cuts such a tail
off before appending.
"""

from __future__ import annotations

import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MAGIC = b"MACBWAL1"
_FRAME = struct.Struct("<II")
_ACTOR = struct.Struct("<H")
_BATCH = struct.Struct("<qIH")
_WIDTH = struct.Struct("<I")
MAX_RECORD = 1 << 30  # a larger length field can only be corruption


@dataclass
class WalRecord:
    actor: str
    seq: int
    n: int
    keys: list[np.ndarray]  # per table: (n, key width) uint8


def pack_record(actor: str, seq: int, keys: list[np.ndarray], n: int) -> bytes:
    """One framed record (frame header + body)."""
    name = actor.encode()
    parts = [_ACTOR.pack(len(name)), name, _BATCH.pack(seq, n, len(keys))]
    for k in keys:
        k = np.ascontiguousarray(k, dtype=np.uint8)
        if k.ndim != 2 or k.shape[0] != n:
            raise ValueError(f"keys must be ({n}, width) uint8, got {k.shape}")
        parts.append(_WIDTH.pack(k.shape[1]))
        parts.append(k.tobytes())
    body = b"".join(parts)
    return _FRAME.pack(len(body), zlib.crc32(body)) + body


def _unpack_body(body: bytes) -> WalRecord:
    (alen,) = _ACTOR.unpack_from(body, 0)
    pos = _ACTOR.size
    actor = body[pos : pos + alen].decode()
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
    (ValueError): it is not ours, and guessing would corrupt counts.
    """
    path = Path(path)
    if not path.exists() or path.stat().st_size == 0:
        return [], 0, False
    data = path.read_bytes()
    if not data.startswith(MAGIC):
        if MAGIC.startswith(data):
            return [], 0, True  # killed while writing the header
        raise ValueError(f"{path}: not a MACB write-ahead log")
    records: list[WalRecord] = []
    pos = len(MAGIC)
    while pos < len(data):
        if pos + _FRAME.size > len(data):
            break
        length, crc = _FRAME.unpack_from(data, pos)
        start, end = pos + _FRAME.size, pos + _FRAME.size + length
        if length > MAX_RECORD or end > len(data):
            break
        body = data[start:end]
        if zlib.crc32(body) != crc:
            break
        try:
            records.append(_unpack_body(body))
        except (ValueError, struct.error, UnicodeDecodeError):
            break
        pos = end
    return records, pos, pos < len(data)


class WriteAheadLog:
    """Append-only log of taken batches; `truncate` empties it after a snapshot."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.records = 0  # appended since the last truncate
        self.bytes = 0
        self._f = open(self.path, "ab")  # noqa: SIM115 (lives as long as the run)
        if self._f.tell() == 0:
            self._f.write(MAGIC)
            self._f.flush()

    @classmethod
    def open(cls, path: Path) -> tuple[WriteAheadLog, list[WalRecord]]:
        """Read what an earlier process logged, cut a torn tail, and open for appending."""
        path = Path(path)
        records, valid, torn = read_wal(path)
        if torn:
            with open(path, "r+b") as f:
                f.truncate(valid)
        wal = cls(path)
        wal.records = len(records)
        wal.bytes = max(0, valid - len(MAGIC))
        return wal, records

    def append(self, actor: str, seq: int, n: int, keys: list[np.ndarray]) -> None:
        """Write one record and hand it to the OS before returning."""
        self.append_many([(actor, seq, n, keys)])

    def append_many(self, batches: list[tuple[str, int, int, list[np.ndarray]]]) -> None:
        """Write several records (actor, seq, n, keys) with one write and one flush.

        The counter logs everything it takes in one burst this way: one system call
        instead of one per batch, and still all on the OS's side before any of them
        is acknowledged.
        """
        data = b"".join(pack_record(actor, seq, keys, n) for actor, seq, n, keys in batches)
        self._f.write(data)
        self._f.flush()
        self.records += len(batches)
        self.bytes += len(data)

    def sync(self) -> None:
        """fsync: what was appended survives the machine too, not only the process."""
        self._f.flush()
        os.fsync(self._f.fileno())

    def truncate(self) -> None:
        """Drop every record (they are in a snapshot now); keep the header."""
        self._f.flush()
        os.truncate(self._f.fileno(), len(MAGIC))
        self.records = 0
        self.bytes = 0

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()
