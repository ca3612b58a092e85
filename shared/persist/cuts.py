"""Consistent cuts of a one-process run: everything needed to continue it exactly.

A cut is taken at an evaluation point E (an episode boundary, its metric row written):
the learner (networks, optimizers, targets, update counter), the count tables, the
collector's and sampler's RNG states and counters, the evaluation envs' RNG states,
and how many replay rows exist. Resuming from it gives the metric rows that not
stopping would have given, bit for bit (timing columns aside), for a fixed lane count.

Files in `DIR/cuts/`:
- `replay.log`: every collected transition, on the one record log (`records.py`): each
  cut appends one record of the rows that came since the last one (obs, act, rew,
  next_obs, done and a stored bonus, float32), never rewriting earlier ones; a cut names
  the row count it covers, and resuming cuts off what lies beyond it (rows appended by a
  run killed after its last cut). Runs written before the record log kept the rows as
  `replay.{field}.f32` columns: they are read and rewritten as a `replay.log` once.
- `cut-EEEEEEEEE.pt`: the rest, a learner checkpoint of kind `cut` (checkpoint.py: the
  one schema the final checkpoint.pt and the learner service's share). The two newest
  are kept: a truncated or corrupt newest cut is refused, naming the file, and the one
  before it is used.
"""

from __future__ import annotations

import logging
import mmap
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shared.persist import checkpoint, records
from shared.persist.checkpoint import CutError
from shared.persist.files import fsync_dir
from shared.persist.records import RecordLog, RecordLogError

log = logging.getLogger("macb.cuts")

CUT_FORMAT = checkpoint.CHECKPOINT_FORMAT
KEEP_CUTS = 2
REPLAY_FIELDS = ("obs", "act", "rew", "next_obs", "done")
REPLAY_LOG, REPLAY_MAGIC, REPLAY_WHAT = "replay.log", b"MACBRPL1", "replay log"
_HEAD = struct.Struct("<qIH")  # first row, rows, fields
_FIELD = struct.Struct("<BI")  # name length, width (float32 values per row)
RECORD_BYTES = 64 << 20  # a record holds at most this many bytes of rows


def pack_rows(first: int, arrays: dict[str, np.ndarray], width: dict[str, int]) -> bytes:
    """One replay record's body: rows [first, first + n) of every field in `width`."""
    cols = {name: np.ascontiguousarray(arrays[name], dtype="<f4") for name in width}
    n = len(next(iter(cols.values()))) if cols else 0
    parts = [_HEAD.pack(first, n, len(cols))]
    for name, data in cols.items():
        if data.size != n * width[name]:
            raise ValueError(f"replay field {name}: {data.shape}, {n} rows of {width[name]}")
        parts += [_FIELD.pack(len(name), width[name]), name.encode(), data.tobytes()]
    return b"".join(parts)


def unpack_rows(body: memoryview) -> tuple[int, int, dict[str, np.ndarray]]:
    """A replay record's first row, its row count and each field's (n, width) rows."""
    first, n, count = _HEAD.unpack_from(body, 0)
    pos, out = _HEAD.size, {}
    for _ in range(count):
        size, width = _FIELD.unpack_from(body, pos)
        pos += _FIELD.size
        name = bytes(body[pos : pos + size]).decode()
        pos += size
        values = np.frombuffer(body, "<f4", count=n * width, offset=pos)
        out[name] = values.reshape(n, width)
        pos += values.nbytes
    if pos != len(body):
        raise ValueError("replay record has trailing bytes")
    return first, n, out


class ReplayLog:
    """The replay rows of a run on disk: records of rows, appended at each cut (see
    the module doc). Read through a read-only mapping, so a resume holds the buffer's
    rows once, not the file as well."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.path = folder / REPLAY_LOG
        folder.mkdir(parents=True, exist_ok=True)
        self._log: RecordLog | None = None
        self._index: list[tuple[int, int, int]] = []  # (first row, rows, frame offset)

    def _map(self) -> bytes | mmap.mmap:
        try:
            return records.mapped(self.path, REPLAY_MAGIC, REPLAY_WHAT)
        except RecordLogError as err:
            raise CutError(str(err)) from None

    def _scan(self) -> tuple[list[tuple[int, int, int]], int]:
        """Each whole record's (first row, rows, frame offset), and where they end."""
        data = self._map()
        if len(data) < len(REPLAY_MAGIC):  # empty, or killed while writing the header
            return [], 0
        starts, valid = records.scan(data, REPLAY_MAGIC)
        index = [(*_HEAD.unpack_from(data, s + records.FRAME.size)[:2], s) for s in starts]
        return index, valid

    def _open(self, start: int, width: dict[str, int]) -> None:
        """This process's first append: a columnar replay of before becomes the log
        (its first `start` rows, the ones the cut names), a torn tail is cut off."""
        if not self.path.exists() and self._legacy_path("obs").exists():
            self._convert_legacy(start, width)
        for name in width:  # a conversion killed before it removed them
            self._legacy_path(name).unlink(missing_ok=True)
        self._index, valid = self._scan()
        self._log = RecordLog.resume(self.path, REPLAY_MAGIC, valid, len(self._index))

    def append(self, arrays: dict[str, np.ndarray], start: int, width: dict[str, int]) -> int:
        """Append rows [start, start + n) (the ones since the last cut), fsynced; returns
        bytes written. Rows from `start` on already in the log (a run killed after
        appending but before its cut was written) are cut off first."""
        if self._log is None:
            self._open(start, width)
        assert self._log is not None
        end = self._index[-1][0] + self._index[-1][1] if self._index else 0
        if end != start:
            self._cut_from(start, width)
        n = len(arrays["obs"])
        step = max(1, RECORD_BYTES // (4 * sum(width.values())))
        written = 0
        for a in range(0, n, step):
            part = {k: arrays[k][a : a + step] for k in width}
            offset = len(REPLAY_MAGIC) + self._log.bytes
            written += self._log.append([pack_rows(start + a, part, width)])
            self._index.append((start + a, len(part["obs"]), offset))
        self._log.sync()
        return written

    def _cut_from(self, start: int, width: dict[str, int]) -> None:
        """Drop the rows from `start` on. A record holding rows on both sides makes the
        log rewritten whole (temporary file, fsync, rename): a kill leaves the old log
        or the new one, never fewer rows than the cut names."""
        assert self._log is not None
        i = sum(1 for first, n, _ in self._index if first + n <= start)
        have = self._index[i - 1][0] + self._index[i - 1][1] if i else 0
        if i < len(self._index) and self._index[i][0] < start:
            self._rewrite_to(i, start, width)
            have = start
        elif i < len(self._index):
            self._log.truncate(self._index[i][2], kept=i)
            self._index = self._index[:i]
        if have != start:
            raise CutError(f"{self.path}: holds {have} rows, a cut appends from row {start}")

    def _rewrite_to(self, i: int, start: int, width: dict[str, int]) -> None:
        """The log as records 0..i-1 and record i's rows before `start`."""
        assert self._log is not None
        self._log.close()
        data = self._map()
        offset = self._index[i][2]
        first, _, rows = unpack_rows(records.body(data, offset))
        prefix = pack_rows(first, {k: v[: start - first] for k, v in rows.items()}, width)
        tmp = self.path.with_name(REPLAY_LOG + ".tmp")
        with open(tmp, "wb") as f:
            f.write(data[:offset])
            f.write(records.frame(prefix))
            f.flush()
            os.fsync(f.fileno())
        del rows, data
        os.replace(tmp, self.path)
        fsync_dir(self.folder)
        self._index = [*self._index[:i], (first, start - first, offset)]
        size = os.path.getsize(self.path)
        self._log = RecordLog.resume(self.path, REPLAY_MAGIC, size, len(self._index))

    def read(self, rows: int, width: dict[str, int], where: Path) -> dict[str, np.ndarray]:
        """The first `rows` rows of every field (rew and done as vectors); CutError
        naming the file if it holds fewer or other fields. Reads only: a columnar
        replay of before is read as it is (the first append converts it)."""
        if not self.path.exists() and self._legacy_path("obs").exists():
            return self._read_legacy(rows, width, where)
        out = {name: np.empty((rows, w), np.float32) for name, w in width.items()}
        have = self._copy_into(out, rows, width)
        if have < rows:
            raise CutError(f"{where}: needs {rows} replay rows, {self.path} holds {have}")
        return {k: v.reshape(-1) if k in ("rew", "done") else v for k, v in out.items()}

    def _copy_into(self, out: dict[str, np.ndarray], rows: int, width: dict[str, int]) -> int:
        """Copy the log's first rows into `out`; how many it holds (up to `rows`)."""
        data = self._map()
        if len(data) < len(REPLAY_MAGIC):
            return 0
        have = 0
        for start in records.scan(data, REPLAY_MAGIC)[0]:
            if have >= rows:
                break
            first, n, cols = unpack_rows(records.body(data, start))
            if first != have:
                raise CutError(f"{self.path}: a record starts at row {first}, not {have}")
            shapes = {k: v.shape[1] for k, v in cols.items()}
            if shapes != width:
                raise CutError(f"{self.path}: rows of {shapes}, the run's are {width}")
            take = min(n, rows - have)
            for name in width:
                out[name][have : have + take] = cols[name][:take]
            have += take
        return have

    # ---- runs written before the record log: one raw float32 file per field
    def _legacy_path(self, name: str) -> Path:
        return self.folder / f"replay.{name}.f32"

    def _read_legacy(self, rows: int, width: dict[str, int], where: Path) -> dict:
        """The columnar files' first `rows` rows."""
        out = {}
        for name, w in width.items():
            p = self._legacy_path(name)
            have = p.stat().st_size // (4 * w) if p.exists() else 0
            if have < rows:
                raise CutError(f"{where}: needs {rows} replay rows, {p} holds {have}")
            data = np.fromfile(p, dtype=np.float32, count=rows * w)
            out[name] = data if name in ("rew", "done") else data.reshape(rows, w)
        return out

    def _convert_legacy(self, rows: int, width: dict[str, int]) -> None:
        """The columnar files' first `rows` rows written as this folder's replay.log,
        whole (temporary file, fsync, rename) before the columns are removed."""
        cols = self._read_legacy(rows, width, self.folder)
        tmp = self.path.with_name(REPLAY_LOG + ".tmp")
        tmp.unlink(missing_ok=True)
        rewritten = RecordLog(tmp, REPLAY_MAGIC)
        step = max(1, RECORD_BYTES // (4 * sum(width.values())))
        for first in range(0, rows, step):
            part = {k: v[first : first + step] for k, v in cols.items()}
            rewritten.append([pack_rows(first, part, width)])
        rewritten.sync()
        rewritten.close()
        os.replace(tmp, self.path)
        fsync_dir(self.folder)
        log.info("%d replay rows of columnar files rewritten as %s", rows, self.path)


@dataclass
class Cut:
    path: Path
    state: dict[str, Any]

    @property
    def episode(self) -> int:
        return int(self.state["episode"])


def clear(folder: Path) -> None:
    """Forget a previous run's cuts and replay log (a fresh run in the same folder)."""
    for path in [*folder.glob("cut-*.pt*"), *folder.glob("replay.*")]:
        path.unlink()


def cut_files(folder: Path) -> list[Path]:
    """Cuts in `folder`, newest first."""
    return sorted(folder.glob("cut-*.pt"), reverse=True)


def write_cut(folder: Path, episode: int, **fields: Any) -> Path:
    """Write the cut for `episode` (a checkpoint of kind `cut`: `fields` are
    `checkpoint.save`'s) and drop all but the newest KEEP_CUTS."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"cut-{episode:09d}.pt"
    checkpoint.save(path, "cut", episode=episode, **fields)
    for old in cut_files(folder)[KEEP_CUTS:]:
        old.unlink(missing_ok=True)
    return path


def read_cut(path: Path, config: dict[str, Any]) -> Cut:
    """Load and check one cut: format, kind, and the config field by field."""
    return Cut(path, checkpoint.load(path, "cut", config))


def latest_cut(folder: Path, config: dict[str, Any]) -> Cut:
    """The newest usable cut; a refused one is logged with its reason and skipped.
    Raises CutError (naming every refused file) when none can be used.

    Refused files newer than the one used are renamed `*.refused` (kept to look at, out
    of the way of the next cuts, which would otherwise be pruned in their favour)."""
    reasons, refused = [], []
    for path in cut_files(folder):
        try:
            cut = read_cut(path, config)
        except CutError as err:
            log.warning("refusing cut %s", err)
            reasons.append(str(err))
            refused.append(path)
            continue
        for bad in refused:
            bad.replace(bad.with_name(bad.name + ".refused"))
        return cut
    if not reasons:
        raise CutError(f"{folder}: no cut to resume from")
    raise CutError("no usable cut: " + "; ".join(reasons))
