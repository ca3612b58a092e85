"""What a burst of batches adds to a run's counts, decided before anything is counted.

The exactly-once rule (`ReceiveCursor`) runs batch by batch in arrival order on a
staging copy of the run's cursor; what one actor has taken in a burst is one contiguous
range (each taken batch starts where the last ended), so it becomes one log record.
The service then hashes the rows, logs them, counts them and only then swaps the
staged cursor in and acknowledges: an acknowledged count is always on disk.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.net.protocol import ReceiveCursor

Batch = tuple[str, int, np.ndarray, np.ndarray]  # actor, seq, obs, act


@dataclass
class Burst:
    staged: ReceiveCursor  # the run's cursor once the burst is taken
    segments: list[tuple[str, int, int]]  # per actor taking rows: (actor, first seq, rows)
    obs: np.ndarray | None  # the rows taken, in segment order (None: nothing taken)
    act: np.ndarray | None

    @property
    def rows(self) -> int:
        return sum(rows for _, _, rows in self.segments)


def plan(cursor: ReceiveCursor, batches: list[Batch]) -> Burst:
    """The rows of `batches` that are new (an overlap's new tail included), by actor."""
    staged = cursor.copy()
    taken: dict[str, tuple[int, list[np.ndarray], list[np.ndarray]]] = {}
    for actor, seq, obs, act in batches:
        start = staged.expected(actor)
        d = staged.take(actor, seq, len(obs))
        if not d.took:
            continue
        if d.skip:
            obs, act = obs[d.skip :], act[d.skip :]
        if actor not in taken:
            taken[actor] = (start, [], [])
        taken[actor][1].append(obs)
        taken[actor][2].append(act)
    if not taken:
        return Burst(staged, [], None, None)
    segments = [(a, start, staged.expected(a) - start) for a, (start, _, _) in taken.items()]
    obs_all = [o for _, parts, _ in taken.values() for o in parts]
    act_all = [a for _, _, parts in taken.values() for a in parts]
    obs = obs_all[0] if len(obs_all) == 1 else np.concatenate(obs_all)
    act = act_all[0] if len(act_all) == 1 else np.concatenate(act_all)
    return Burst(staged, segments, obs, act)
