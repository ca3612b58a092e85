"""The one record log: an append-only file of CRC-framed binary records.

Every log the platform keeps is one, told apart by its 8-byte magic: the learner's and
the counter's write-ahead logs (`wal.py`: each batch taken, logged before it is
acknowledged) and a one-process run's replay log (`cuts.py`: the rows collected since
the last cut, appended when the cut is written). Each kind packs its own fixed binary
body; no msgpack, no pickle.

File layout::

    header  magic (8 bytes)
    record  <II  body length, CRC-32 of the body; then the body

A record cut short by a kill, or one whose CRC does not match, ends the log: nothing
after it was ever committed (acknowledged, or named by a cut), so `RecordLog.open` cuts
that tail off before appending. A file with another magic is refused, naming it.
"""

from __future__ import annotations

import mmap
import os
import struct
import zlib
from collections.abc import Iterable
from pathlib import Path

FRAME = struct.Struct("<II")
MAGIC_BYTES = 8
MAX_RECORD = 1 << 30  # a larger length field can only be corruption


class RecordLogError(ValueError):
    """A file that is not the log it should be: the message names it."""


def scan(data: bytes | memoryview | mmap.mmap, magic: bytes) -> tuple[list[int], int]:
    """The start offset of each whole record after the header (its frame's offset)
    and the length of the valid prefix. `data` must begin with `magic`."""
    starts: list[int] = []
    pos = len(magic)
    while pos + FRAME.size <= len(data):
        length, crc = FRAME.unpack_from(data, pos)
        end = pos + FRAME.size + length
        if length > MAX_RECORD or end > len(data):
            break
        if zlib.crc32(data[pos + FRAME.size : end]) != crc:
            break
        starts.append(pos)
        pos = end
    return starts, pos


def body(data: bytes | memoryview | mmap.mmap, start: int) -> memoryview:
    """The body of the record whose frame is at `start` (a view, no copy)."""
    (length, _) = FRAME.unpack_from(data, start)
    return memoryview(data)[start + FRAME.size : start + FRAME.size + length]


def frame(payload: bytes) -> bytes:
    """One record: its frame header, then `payload`."""
    return FRAME.pack(len(payload), zlib.crc32(payload)) + payload


def mapped(path: Path, magic: bytes, what: str) -> bytes | mmap.mmap:
    """The file mapped read-only (b"" if missing or empty), its header checked as
    `read` does: nothing of it is copied until read. The mapping closes when the last
    view of it goes (no explicit close: a view still held would make that fail)."""
    path = Path(path)
    if not path.exists() or path.stat().st_size == 0:
        return b""
    with open(path, "rb") as f:
        data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    head = data[:MAGIC_BYTES]
    if head != magic and not (magic.startswith(head) and len(data) < MAGIC_BYTES):
        raise RecordLogError(f"{path}: not a MACB {what} (header {head!r})")
    return data


def read(path: Path, magic: bytes, what: str) -> tuple[bytes, list[int], int, bool]:
    """A whole log: (its bytes, each record's frame offset, the valid prefix's length,
    whether a tail past it was cut short). A missing or empty file is an empty log; a
    file killed while its header was written is an empty log with a torn tail; a file
    with another header raises RecordLogError naming it."""
    path = Path(path)
    if not path.exists() or path.stat().st_size == 0:
        return b"", [], 0, False
    data = path.read_bytes()
    if not data.startswith(magic):
        if magic.startswith(data):
            return data, [], 0, True
        raise RecordLogError(f"{path}: not a MACB {what} (header {data[:MAGIC_BYTES]!r})")
    starts, valid = scan(data, magic)
    return data, starts, valid, valid < len(data)


class RecordLog:
    """A log open for appending. `open` reads what an earlier process wrote and cuts a
    torn tail; `append` hands records to the OS before returning (what a killed process
    leaves), `sync` makes them survive the machine too."""

    def __init__(self, path: Path, magic: bytes) -> None:
        if len(magic) != MAGIC_BYTES:
            raise ValueError(f"a log's magic is {MAGIC_BYTES} bytes, got {magic!r}")
        self.path, self.magic = Path(path), magic
        self.records = 0  # since the last truncate
        self.bytes = 0
        self._f = open(self.path, "ab")  # noqa: SIM115 (lives as long as its owner)
        if self._f.tell() == 0:
            self._f.write(magic)
            self._f.flush()

    @classmethod
    def open(cls, path: Path, magic: bytes, what: str) -> tuple[RecordLog, bytes, list[int]]:
        """The log at `path` for appending, with what it held: (log, its bytes, each
        whole record's frame offset). A torn tail is cut off first."""
        data, starts, valid, _ = read(path, magic, what)
        return cls.resume(path, magic, valid, len(starts)), data, starts

    @classmethod
    def resume(cls, path: Path, magic: bytes, valid: int, records: int) -> RecordLog:
        """The log at `path` for appending after a read found `records` whole records
        in its first `valid` bytes: anything past them (a torn tail) is cut off."""
        path = Path(path)
        if path.exists() and path.stat().st_size > valid:
            os.truncate(path, valid)
        log = cls(path, magic)
        log.records = records
        log.bytes = max(0, valid - len(magic))
        return log

    def append(self, payloads: Iterable[bytes]) -> int:
        """Write records (one write, one flush); the bytes written. A payload over
        MAX_RECORD is refused (ValueError): it could not be read back."""
        frames = [frame(p) for p in payloads]
        if any(len(f) - FRAME.size > MAX_RECORD for f in frames):
            raise ValueError(f"{self.path}: a record over {MAX_RECORD} bytes")
        data = b"".join(frames)
        self._f.write(data)
        self._f.flush()
        self.records += len(frames)
        self.bytes += len(data)
        return len(data)

    def sync(self) -> None:
        """fsync: what was appended survives the machine too, not only the process."""
        self._f.flush()
        os.fsync(self._f.fileno())

    def truncate(self, offset: int | None = None, kept: int = 0) -> None:
        """Drop every record from `offset` (a record's frame offset, `kept` records
        before it; default: all of them, keeping the header)."""
        offset = len(self.magic) if offset is None else max(offset, len(self.magic))
        self._f.flush()
        os.truncate(self._f.fileno(), offset)
        self.records = kept
        self.bytes = offset - len(self.magic)

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()
