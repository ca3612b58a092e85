"""What the counter holds for each run it counts."""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

from shared.config import TrainConfig
from shared.core.exploration import CountExploration
from shared.net.protocol import ReceiveCursor
from shared.persist.wal import WriteAheadLog

LATENCY_WINDOW = 1000


@dataclass
class RunState:
    """One run's tables, expected numbers, log and stats."""

    config: TrainConfig
    explorer: CountExploration
    obs_dim: int
    act_dim: int
    path: Path
    wal: WriteAheadLog
    # Next expected number per actor, and the duplicate rows / gaps seen (shared.net.protocol):
    # once opened, of the run's actors alone and whole batches only, as the learner's.
    cursor: ReceiveCursor = field(default_factory=ReceiveCursor)
    counted: int = 0
    run_rejects: int = 0
    queries: int = 0
    uncounted_rows_queried: int = 0
    snapshots: int = 0
    dirty: bool = False
    latencies: deque = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    rate: float = 0.0
    rate_t: float = field(default_factory=time.monotonic)
    rate_counted: int = 0
    closed: bool = False
    learner: str | None = None  # the run ends for the counter when its learner completes
    # The run's actors (its assignment's), whose batches alone are counted; None: not
    # known (a folder without a readable assign.json), any actor's.
    actors: tuple[str, ...] | None = None

    @property
    def lockstep(self) -> bool:
        """interleave lockstep: a batch is one step, not one episode."""
        return self.config.interleave == "lockstep"
