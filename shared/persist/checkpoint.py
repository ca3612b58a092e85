"""The one learner checkpoint schema: a one-process run's cuts (`cuts/cut-E.pt`), its
final `checkpoint.pt` and the learner service's `checkpoint.pt` are all written by
`save` and read by `load`.

A checkpoint is a `torch.save` file of tensors and primitives only, read with
`torch.load(weights_only=True)` (no pickle), written atomically (files.atomic_write).
Its fields:

- `format` (CHECKPOINT_FORMAT: an earlier version refuses the file by it, rather
  than misreading a field) and `kind`: `cut`, `final`, `service` or `best` (a run with
  `early_stop`: its best evaluation point's learner, without tables);
- `config`: the run's config as JSON (a checkpoint of another config is refused,
  naming the first field that differs);
- `learner`: the learner's state_dict (networks, optimizers, targets, update count);
- `counters`: the kind's step, episode and update counters (plain numbers);
- `rng`: the random states as JSON (`sampler` always; a cut also `collector`, `eval_envs`);
- `tables`: the count tables as {"table0": {keys, counts, total, key_bytes}, ...}, where
  the kind keeps them (the service's are the counter's); a count-min sketch's
  (`count_sketch`) as {"table0": {sketch: {cells, total, count1, distinct, width, depth,
  conservative}, key_bytes}, ...};
- the kind's own fields: a cut's `episode`, `replay_rows`, `torch_rng`; the service's
  `ingested_pos` (each actor's next transition) and `boundaries` (episode ends owed).

Files of format 1 carry no `kind` (their place says which they are); the learner
service's kept its sampler state as the whole `rng`; the trainer's cuts kept `tables`
as a list, its final checkpoint had no `format`. `load` reads all of them.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from shared.core.counting import Counts, CountSketch, CountTable
from shared.persist.files import atomic_write

CHECKPOINT_FORMAT = 2  # 1: the same fields, before `kind` (still read)
KINDS = ("cut", "final", "service", "best")


class CutError(ValueError):
    """A checkpoint that cannot be used: the message names the file and what is wrong."""


class UnreadableCheckpoint(CutError):
    """The file is not a whole checkpoint (cut short by a kill, or not one at all), as
    opposed to a whole one of another config or format."""


def save(
    path: Path,
    kind: str,
    config: dict[str, Any],
    learner: dict[str, Any],
    counters: dict[str, Any],
    rng: dict[str, Any] | None = None,
    tables: Sequence[Counts] | None = None,
    previous: Path | None = None,
    **own: Any,
) -> None:
    """Write a checkpoint of `kind` to `path` atomically (`previous`: the old file is
    kept there, moved aside only once the new one is on disk)."""
    if kind not in KINDS:
        raise ValueError(f"checkpoint kind {kind!r}, not one of {KINDS}")
    state = {
        "format": CHECKPOINT_FORMAT,
        "kind": kind,
        "config": json.dumps(config),
        "learner": learner,
        "counters": counters,
        **({} if rng is None else {"rng": json.dumps(rng)}),
        **({} if tables is None else {"tables": tables_state(tables)}),
        **own,
    }
    atomic_write(path, lambda f: torch.save(state, f), previous)


BEST = "best.pt"


def save_best(path: Path, config: dict[str, Any], learner: dict[str, Any], row: dict) -> None:
    """The best evaluation point's learner (`early_stop`), as a checkpoint of kind
    `best`: `learner` (networks and optimizers at the point whose metric `row` it is),
    the point's episode, steps and success, no tables (the last weights and the tables
    are checkpoint.pt's). The trainer and the learner service both write it here, so
    a run's best.pt is one file whichever ran it."""
    counters = {
        "episode": int(row["episode"]),
        "env_steps": int(row["env_steps"]),
        "success_rate": float(row["success_rate"]),
    }
    save(path, "best", config, learner, counters)


def load(
    path: Path, kind: str | tuple[str, ...], config: dict[str, Any] | None = None
) -> dict[str, Any]:
    """A checkpoint of `kind` (or one of several) from `path`, checked: CutError naming
    the file if it is of another format, kind or (with `config`) config, then
    UnreadableCheckpoint if it does not load as one or lacks its learner or counters.
    `rng` comes back decoded, with `sampler` in it."""
    kinds = (kind,) if isinstance(kind, str) else kind
    try:
        state = torch.load(path, weights_only=True)
    except Exception as err:  # truncated, or not a torch file at all
        raise UnreadableCheckpoint(f"{path}: unreadable ({type(err).__name__}: {err})") from None
    if not isinstance(state, dict):
        raise UnreadableCheckpoint(f"{path}: not a checkpoint (a {type(state).__name__})")
    found = state.get("format", 1 if "final" in kinds else None)
    if found not in (1, CHECKPOINT_FORMAT):
        raise CutError(f"{path}: cut format {found}, this version reads {CHECKPOINT_FORMAT}")
    if state.get("kind", kinds[0]) not in kinds:
        raise CutError(f"{path}: a {state['kind']} checkpoint, not a {' or '.join(kinds)} one")
    try:
        saved = json.loads(state["config"])
    except (KeyError, TypeError, ValueError) as err:
        raise CutError(f"{path}: no readable config ({err})") from None
    if config is not None and (diff := config_difference(saved, config)) is not None:
        raise CutError(f"{path}: written by another config ({diff})")
    if "learner" not in state or "counters" not in state:
        raise UnreadableCheckpoint(f"{path}: not a whole checkpoint (no learner or counters)")
    if "rng" in state:
        rng = json.loads(state["rng"])
        state["rng"] = rng if "sampler" in rng else {"sampler": rng}  # the service's, before
    return state


def tables_state(tables: Sequence[Counts]) -> dict[str, dict[str, Any]]:
    """Count tables as a checkpoint holds them."""
    out: dict[str, dict[str, Any]] = {}
    for t, table in enumerate(tables):
        if isinstance(table, CountSketch):
            sketch = table.state()
            sketch["cells"] = torch.from_numpy(sketch["cells"])
            out[f"table{t}"] = {"sketch": sketch, "key_bytes": table.key_bytes}
            continue
        keys, counts = table.to_arrays()
        out[f"table{t}"] = {
            "keys": torch.from_numpy(keys),  # to_arrays' own new arrays: no copy
            "counts": torch.from_numpy(counts),
            "total": table.total,
            "key_bytes": table.key_bytes,
        }
    return out


def load_tables(tables: list[Counts], state: Any, where: Path) -> None:
    """A checkpoint's count tables into `tables` (in place), refused naming `where`
    if they are not the run's (exact tables for a sketch or the other way round, another
    sketch shape); the list form of earlier cuts is read too."""
    saved = [state[f"table{t}"] for t in range(len(state))] if isinstance(state, dict) else state
    if len(saved) != len(tables):
        raise CutError(f"{where}: {len(saved)} count tables, the run has {len(tables)}")
    for t, one in enumerate(saved):
        if int(one["key_bytes"]) != tables[t].key_bytes:
            raise CutError(f"{where}: table {t} has {one['key_bytes']}-byte keys")
        table = tables[t]
        if ("sketch" in one) != isinstance(table, CountSketch):
            kinds = ("an exact table", "a count-min sketch")
            raise CutError(
                f"{where}: table {t} is {kinds['sketch' in one]}, the run has "
                f"{kinds[isinstance(table, CountSketch)]} (count_sketch)"
            )
        if isinstance(table, CountSketch):
            sketch = {**one["sketch"], "cells": one["sketch"]["cells"].numpy()}
            try:
                table.load_state(sketch)
            except ValueError as err:
                raise CutError(f"{where}: table {t}: {err}") from None
            continue
        keys, counts = one["keys"].numpy(), one["counts"].numpy()
        tables[t] = CountTable.from_arrays(keys, counts, int(one["total"]))


def config_difference(
    saved: dict[str, Any], config: dict[str, Any], where: tuple[str, str] = ("the cut", "the run")
) -> str | None:
    """The first field where a checkpoint's config and the run's differ, as 'field: a in
    the cut, b in the run' (`where` names the two). A key the saved config lacks counts
    as its default (a run written before the key existed ran with what the default
    does), so adding a config key does not make earlier runs unresumable."""
    from shared.config import TrainConfig

    fields = TrainConfig.model_fields
    for key in sorted(set(saved) | set(config)):
        if key not in saved and key in fields and config.get(key) == _default(fields[key]):
            continue
        if saved.get(key) != config.get(key):
            return f"{key}: {saved.get(key)!r} in {where[0]}, {config.get(key)!r} in {where[1]}"
    return None


def folder_config_difference(folder: Path, config: dict[str, Any]) -> str | None:
    """Why run folder `folder` holds a run of another config than `config` (as JSON):
    the first field that differs ('field: a in the folder, b in the run', by
    `config_difference`), or that its config.json does not read. None when it has no
    config.json yet, or the same config. The one rule of going on in a run folder: the
    local runner, the trainer's resume and the counter service each ask it."""
    path = folder / "config.json"
    if not path.exists():
        return None
    try:
        written = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        return f"{path} does not read ({err})"
    if not isinstance(written, dict):
        return f"{path} holds no config (not a JSON map)"
    return config_difference(written, config, ("the folder", "the run"))


def _default(field: Any) -> Any:
    """A config field's default as JSON (what model_dump(mode="json") writes)."""
    value = field.default
    return list(value) if isinstance(value, tuple) else value
