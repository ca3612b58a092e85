"""Consistent cuts of a one-process run: everything needed to continue it exactly.

A cut is taken at an evaluation point E (an episode boundary, its metric row written):
the learner (networks, optimizers, targets, update counter), the count tables, the
collector's and sampler's RNG states and counters, the evaluation envs' RNG states,
and how many replay rows exist. Resuming from it gives the metric rows that not
stopping would have given, bit for bit (timing columns aside), for a fixed lane count.

Files in `DIR/cuts/`:
- `replay.{obs,act,rew,next_obs,done}.f32`: every collected transition, appended as raw
  float32 rows at each cut (never rewritten: a cut writes only what came since the
  last one); a cut names the row count it covers, and resuming truncates what lies
  beyond it (rows written by a run killed after its last cut).
- `cut-EEEEEEEEE.pt`: the rest, written atomically (temporary file, fsync, rename) in
  `torch.save` format with tensors and primitives only, loaded with
  `torch.load(weights_only=True)`; it carries `format` and the run's config. The two
  newest are kept: a truncated or corrupt newest cut is refused, naming the file, and
  the one before it is used.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from shared.core.counting import CountTable
from shared.persist.files import atomic_write

log = logging.getLogger("macb.cuts")

CUT_FORMAT = 1
KEEP_CUTS = 2
REPLAY_FIELDS = ("obs", "act", "rew", "next_obs", "done")


class CutError(ValueError):
    """A cut that cannot be used: the message names the file and what is wrong."""


def atomic_torch_save(obj: Any, path: Path, previous: Path | None = None) -> None:
    """Write `obj` to `path` so that a crash leaves the old file or the new one, whole.

    With `previous`, the old file is kept there, moved aside only once the new one is
    written and fsynced: a kill at any point leaves a good file at `path` or, between
    the two renames, at `previous`."""
    atomic_write(path, lambda f: torch.save(obj, f), previous)


def tables_state(tables: Sequence[CountTable]) -> list[dict[str, Any]]:
    out = []
    for table in tables:
        keys, counts = table.to_arrays()
        out.append(
            {
                "keys": torch.from_numpy(keys.copy()),
                "counts": torch.from_numpy(counts),
                "total": table.total,
                "key_bytes": table.key_bytes,
            }
        )
    return out


def load_tables(tables: list[CountTable], state: list[dict[str, Any]], where: Path) -> None:
    if len(state) != len(tables):
        raise CutError(f"{where}: {len(state)} count tables, the run has {len(tables)}")
    for t, saved in enumerate(state):
        if int(saved["key_bytes"]) != tables[t].key_bytes:
            raise CutError(f"{where}: table {t} has {saved['key_bytes']}-byte keys")
        keys, counts = saved["keys"].numpy(), saved["counts"].numpy()
        tables[t] = CountTable.from_arrays(keys, counts, int(saved["total"]))


class ReplayLog:
    """The replay rows of a run on disk, appended at each cut (see the module doc)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)

    def path(self, name: str) -> Path:
        return self.folder / f"replay.{name}.f32"

    def rows_on_disk(self, width: dict[str, int]) -> int:
        sizes = []
        for name in width:
            p = self.path(name)
            sizes.append(p.stat().st_size // (4 * width[name]) if p.exists() else 0)
        return min(sizes)

    def append(self, arrays: dict[str, np.ndarray], start: int, width: dict[str, int]) -> int:
        """Append rows [start, start + n) (the ones since the last cut); returns bytes
        written. Rows beyond `start` already on disk (a run killed after appending but
        before its cut was written) are cut off first."""
        written = 0
        for name in width:  # REPLAY_FIELDS, and a stored bonus where the run keeps one
            data = np.ascontiguousarray(arrays[name], dtype=np.float32)
            with open(self.path(name), "ab") as f:
                f.truncate(start * 4 * width[name])
                f.write(data.tobytes())
                f.flush()
                os.fsync(f.fileno())
            written += data.nbytes
        return written

    def read(self, rows: int, width: dict[str, int], where: Path) -> dict[str, np.ndarray]:
        out = {}
        for name in width:
            p, w = self.path(name), width[name]
            have = p.stat().st_size // (4 * w) if p.exists() else 0
            if have < rows:
                raise CutError(f"{where}: needs {rows} replay rows, {p} holds {have}")
            data = np.fromfile(p, dtype=np.float32, count=rows * w)
            out[name] = data if name in ("rew", "done") else data.reshape(rows, w)
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
    for path in [*folder.glob("cut-*.pt*"), *folder.glob("replay.*.f32")]:
        path.unlink()


def cut_files(folder: Path) -> list[Path]:
    """Cuts in `folder`, newest first."""
    return sorted(folder.glob("cut-*.pt"), reverse=True)


def write_cut(folder: Path, episode: int, state: dict[str, Any]) -> Path:
    """Write the cut for `episode` and drop all but the newest KEEP_CUTS."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"cut-{episode:09d}.pt"
    atomic_torch_save({"format": CUT_FORMAT, "episode": episode, **state}, path)
    for old in cut_files(folder)[KEEP_CUTS:]:
        old.unlink(missing_ok=True)
    return path


def config_difference(saved: dict[str, Any], config: dict[str, Any]) -> str | None:
    """The first field where a cut's config and the run's differ, as 'field: a != b'.

    A key the saved config lacks counts as its default (a run written before the key
    existed ran with what the default does), so adding a config key does not make
    earlier runs unresumable."""
    from shared.config import TrainConfig

    fields = TrainConfig.model_fields
    for key in sorted(set(saved) | set(config)):
        if key not in saved and key in fields and config.get(key) == _default(fields[key]):
            continue
        if saved.get(key) != config.get(key):
            return f"{key}: {saved.get(key)!r} in the cut, {config.get(key)!r} in the run"
    return None


def read_cut(path: Path, config: dict[str, Any]) -> Cut:
    """Load and check one cut: format, and the config field by field."""
    try:
        state = torch.load(path, weights_only=True)
    except Exception as err:  # truncated or not a torch file at all
        raise CutError(f"{path}: unreadable ({type(err).__name__}: {err})") from None
    if not isinstance(state, dict) or "format" not in state:
        raise CutError(f"{path}: not a cut (no format field)")
    if state["format"] != CUT_FORMAT:
        raise CutError(f"{path}: cut format {state['format']}, this version reads {CUT_FORMAT}")
    try:
        saved = json.loads(state["config"])
    except (KeyError, ValueError) as err:
        raise CutError(f"{path}: no readable config ({err})") from None
    diff = config_difference(saved, config)
    if diff is not None:
        raise CutError(f"{path}: written by another config ({diff})")
    return Cut(path, state)


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


def _default(field: Any) -> Any:
    """A config field's default as JSON (what model_dump(mode="json") writes)."""
    value = field.default
    return list(value) if isinstance(value, tuple) else value
