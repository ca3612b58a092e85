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
LEGACY_CHUNK = 1 << 16  # rows per record when a columnar replay is rewritten as a log


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
    """The replay rows of a run on disk: one record per cut (see the module doc)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.path = folder / REPLAY_LOG
        folder.mkdir(parents=True, exist_ok=True)
        self._log: RecordLog | None = None
        self._index: list[tuple[int, int, int]] = []  # (first row, rows, frame offset)

    def _read(self) -> tuple[bytes, list[tuple[int, int, int]]]:
        try:
            data, starts, _, _ = records.read(self.path, REPLAY_MAGIC, REPLAY_WHAT)
        except RecordLogError as err:
            raise CutError(str(err)) from None
        index = []
        for start in starts:
            first, n, _ = _HEAD.unpack_from(records.body(data, start), 0)
            index.append((first, n, start))
        return data, index

    def append(self, arrays: dict[str, np.ndarray], start: int, width: dict[str, int]) -> int:
        """Append rows [start, start + n) (the ones since the last cut) as one record,
        fsynced; returns bytes written. Rows from `start` on already in the log (a run
        killed after appending but before its cut was written) are cut off first."""
        if self._log is None:
            self._index = self._read()[1]  # also refuses a file that is not a replay log
            self._log = RecordLog.open(self.path, REPLAY_MAGIC, REPLAY_WHAT)[0]
        end = self._index[-1][0] + self._index[-1][1] if self._index else 0
        if end != start:
            self._cut_from(start, width)
        offset = len(REPLAY_MAGIC) + self._log.bytes
        n = len(arrays["obs"])
        written = self._log.append([pack_rows(start, arrays, width)])
        self._log.sync()
        self._index.append((start, n, offset))
        return written

    def _cut_from(self, start: int, width: dict[str, int]) -> None:
        """Drop the rows from `start` on; a record holding rows on both sides is
        rewritten with the ones before."""
        assert self._log is not None
        keep = [i for i, (first, n, _) in enumerate(self._index) if first + n <= start]
        i = len(keep)
        have = self._index[i - 1][0] + self._index[i - 1][1] if i else 0
        straddle = i < len(self._index) and self._index[i][0] < start
        prefix = None
        if straddle:
            data, _ = self._read()
            first, _, rows = unpack_rows(records.body(data, self._index[i][2]))
            prefix = (first, {k: v[: start - first] for k, v in rows.items()})
        if i < len(self._index):
            self._log.truncate(self._index[i][2], kept=i)
            self._index = self._index[:i]
        if prefix is not None:
            first, rows = prefix
            offset = len(REPLAY_MAGIC) + self._log.bytes
            self._log.append([pack_rows(first, rows, {k: width[k] for k in rows})])
            self._index.append((first, start - first, offset))
            have = start
        if have != start:
            raise CutError(f"{self.path}: holds {have} rows, a cut appends from row {start}")

    def read(self, rows: int, width: dict[str, int], where: Path) -> dict[str, np.ndarray]:
        """The first `rows` rows of every field (rew and done as vectors); CutError
        naming the file if it holds fewer or other fields."""
        if not self.path.exists() and self._legacy_path("obs").exists():
            return self._read_legacy(rows, width, where)
        data, index = self._read()
        parts: dict[str, list[np.ndarray]] = {name: [] for name in width}
        have = 0
        for first, _, start in index:
            if have >= rows:
                break
            if first != have:
                raise CutError(f"{self.path}: a record starts at row {first}, not {have}")
            _, n, cols = unpack_rows(records.body(data, start))
            shapes = {k: v.shape[1] for k, v in cols.items()}
            if shapes != width:
                raise CutError(f"{self.path}: rows of {shapes}, the run's are {width}")
            take = min(n, rows - have)
            for name in width:
                parts[name].append(cols[name][:take])
            have += take
        if have < rows:
            raise CutError(f"{where}: needs {rows} replay rows, {self.path} holds {have}")
        out = {}
        for name, w in width.items():
            cat = np.concatenate(parts[name]) if parts[name] else np.zeros((0, w), np.float32)
            out[name] = cat.reshape(-1) if name in ("rew", "done") else cat.reshape(rows, w)
        return out

    # ---- runs written before the record log: one raw float32 file per field
    def _legacy_path(self, name: str) -> Path:
        return self.folder / f"replay.{name}.f32"

    def _read_legacy(self, rows: int, width: dict[str, int], where: Path) -> dict:
        """The columnar files' first `rows` rows, rewritten as this folder's replay.log
        (whole before the columns are removed: a kill leaves one or the other)."""
        out = {}
        for name, w in width.items():
            p = self._legacy_path(name)
            have = p.stat().st_size // (4 * w) if p.exists() else 0
            if have < rows:
                raise CutError(f"{where}: needs {rows} replay rows, {p} holds {have}")
            data = np.fromfile(p, dtype=np.float32, count=rows * w)
            out[name] = data if name in ("rew", "done") else data.reshape(rows, w)
        tmp = self.path.with_name(REPLAY_LOG + ".tmp")
        tmp.unlink(missing_ok=True)
        rewritten = RecordLog(tmp, REPLAY_MAGIC)
        for first in range(0, rows, LEGACY_CHUNK):
            part = {k: v[first : first + LEGACY_CHUNK] for k, v in out.items()}
            rewritten.append([pack_rows(first, part, width)])
        rewritten.sync()
        rewritten.close()
        os.replace(tmp, self.path)
        fsync_dir(self.folder)
        for name in width:
            self._legacy_path(name).unlink(missing_ok=True)
        log.info("%s: %d replay rows of columnar files rewritten as %s", where, rows, self.path)
        return out


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
