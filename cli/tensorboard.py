"""Metric rows as TensorBoard scalars, written with torch's SummaryWriter.

One folder per run (TensorBoard shows each subfolder of its --logdir as a run); every
numeric field of a row is a scalar of that name at step = the row's `episode`, so the
charts line up with metrics.csv and the dashboard. `macb train --tensorboard DIR`
writes rows as they come; `macb export ID --tensorboard DIR` writes a cluster run's
stored points afterwards. The event files are the library's own (tensorboard's
protobuf records), readable by TensorBoard and by its EventAccumulator.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

EVENT_GLOB = "events.out.tfevents.*"
#: Fields of a row that are not metrics: the step itself and the store's point number.
NOT_SCALARS = frozenset({"episode", "seq"})


def run_folder_name(*parts: str) -> str:
    """A folder name from readable parts ("cen-macb", "seed0"): characters a path or a
    shell would trip on become `_`, so an arm's name can name its folder."""
    text = "-".join(p for p in parts if p)
    return re.sub(r"[^A-Za-z0-9._=+,-]+", "_", text).strip("_") or "run"


def scalars(row: dict[str, Any]) -> dict[str, float]:
    """The row's numbers (booleans and text are not metrics)."""
    return {
        k: float(v)
        for k, v in row.items()
        if k not in NOT_SCALARS and isinstance(v, int | float) and not isinstance(v, bool)
    }


class TensorBoardRun:
    """One run's event file. `fresh` removes the folder's earlier event files (a run
    written again from its start); `purge_from` hides, in TensorBoard, what an earlier
    life of the run wrote from that step on (a resumed run repeats those steps)."""

    def __init__(self, folder: Path, fresh: bool = True, purge_from: int | None = None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        folder.mkdir(parents=True, exist_ok=True)
        if fresh:
            for old in folder.glob(EVENT_GLOB):
                old.unlink()
        self.folder = folder
        self.writer = SummaryWriter(str(folder), purge_step=purge_from, flush_secs=30)

    def write(self, row: dict[str, Any]) -> None:
        """One evaluation point: every numeric field at step = its episode."""
        episode = row.get("episode")
        if not isinstance(episode, int):
            raise ValueError(f"a metric row needs an integer episode, got {episode!r}")
        for name, value in scalars(row).items():
            self.writer.add_scalar(name, value, episode)
        self.writer.flush()

    def write_all(self, rows: Iterable[dict[str, Any]]) -> int:
        n = 0
        for row in rows:
            self.write(row)
            n += 1
        return n

    def close(self) -> None:
        self.writer.close()

    def __enter__(self) -> TensorBoardRun:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
