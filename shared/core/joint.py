"""Joint vectors s = o_1 || ... || o_N: where each agent's block starts.

numpy only, so the task adapters (which import mpe2) and the learners (which import
torch) share one definition without importing each other.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def offsets(dims: Sequence[int]) -> list[int]:
    """[0, d_1, d_1 + d_2, ..., sum(dims)]: agent i's block is [offsets[i], offsets[i + 1])."""
    return [0, *np.cumsum(dims).tolist()]
