"""Which vectors are counted, in how many tables, and the bonus each agent receives.

Dis-MACB: one table per agent over o_i || a_i; agent i gets its own bonus.
Cen-MACB: one table over the joint s || x (s = o_1..o_N, x = a_1..a_N); every agent
gets the same bonus. "state" keys drop the actions; hash "none" keys the vector
rounded to 2 decimals. "constant" is a control arm: the same shift beta on every
reward with no counting at all, separating the effect of counting from the effect of
shifting the reward (docs/reproduce.md, "Arms and controls").

Everything works on joint batches laid out as the replay buffer stores them:
obs (B, sum obs_dims) and act (B, sum act_dims), agents in task order.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from shared.core.counting import Counts, CountSketch, CountTable, count_bonus
from shared.core.joint import offsets
from shared.core.simhash import RawKey, RoundKey, SimHash

EXPLORE_MODES = ("none", "dis-macb", "cen-macb", "constant")


@dataclass(frozen=True)
class ExploreSpec:
    mode: str = "cen-macb"
    beta: float = 0.8
    k: int = 512
    hash: str = "simhash"  # "simhash", "none" (round to `round` or 2 decimals), "raw" (bytes)
    key: str = "state-action"  # or "state"
    seed: int = 0
    # Decimals the counted vector is rounded to before it is keyed (None: not rounded;
    # hash "none": the key's decimals, 2 when None); the thesis code rounds Cen-MACB's
    # joint vector to 2 whatever its strategy.
    round: int | None = None
    # (width, depth, conservative) of a count-min sketch per table; None: exact tables.
    sketch: tuple[int, int, bool] | None = None


class CountExploration:
    """Turns joint transitions into per-table keys, counts them, and prices bonuses."""

    def __init__(self, spec: ExploreSpec, obs_dims: tuple[int, ...], act_dims: tuple[int, ...]):
        if spec.mode not in EXPLORE_MODES:
            raise ValueError(f"explore mode must be one of {EXPLORE_MODES}, got {spec.mode!r}")
        self.spec = spec
        self.obs_dims = tuple(obs_dims)
        self.act_dims = tuple(act_dims)
        self.n_agents = len(obs_dims)
        self._oo = offsets(self.obs_dims)
        self._ao = offsets(self.act_dims)
        with_act = spec.key == "state-action"
        if spec.mode == "dis-macb":
            self.table_dims = [o + (a if with_act else 0) for o, a in zip(obs_dims, act_dims)]
        elif spec.mode == "cen-macb":
            self.table_dims = [sum(obs_dims) + (sum(act_dims) if with_act else 0)]
        else:
            self.table_dims = []
        self.hashers: list[SimHash | RoundKey | RawKey] = [
            SimHash(d, spec.k, seed=spec.seed + t)
            if spec.hash == "simhash"
            else RawKey(d)
            if spec.hash == "raw"
            else RoundKey(d, 2 if spec.round is None else spec.round)
            for t, d in enumerate(self.table_dims)
        ]
        self.tables: list[Counts] = [
            self._table(h.key_bytes, t) for t, h in enumerate(self.hashers)
        ]

    def _table(self, key_bytes: int, t: int) -> Counts:
        """Table t's counts: exact, or a sketch hashed with a seed of its own."""
        if self.spec.sketch is None:
            return CountTable(key_bytes)
        width, depth, conservative = self.spec.sketch
        return CountSketch(
            key_bytes, width, depth, seed=self.spec.seed + t, conservative=conservative
        )

    @property
    def counting(self) -> bool:
        return bool(self.tables)

    def vectors(self, obs: np.ndarray, act: np.ndarray) -> list[np.ndarray]:
        """The vector each table counts, one (B, D_t) array per table."""
        with_act = self.spec.key == "state-action"
        if self.spec.mode == "cen-macb":
            return [np.concatenate([obs, act], axis=1) if with_act else obs]
        if self.spec.mode == "dis-macb":
            out = []
            for i in range(self.n_agents):
                o = obs[:, self._oo[i] : self._oo[i + 1]]
                a = act[:, self._ao[i] : self._ao[i + 1]]
                out.append(np.concatenate([o, a], axis=1) if with_act else o)
            return out
        return []

    def keys(self, obs: np.ndarray, act: np.ndarray) -> list[np.ndarray]:
        """Packed keys per table: (B, key_bytes) uint8 each."""
        vectors = self.vectors(obs, act)
        if self.spec.round is not None and self.spec.hash != "none":
            # (hash none: RoundKey keys the vector at these decimals itself.) Any key is
            # of the rounded vector, as the thesis code's Cen path rounds before any
            # strategy. The same float32 values are rounded at collection and at sampling,
            # so a sampled row always finds its counted key (the thesis code rounded float64
            # at one and float32 at the other: docs/fidelity.md, row C4).
            vectors = [np.round(v, self.spec.round) for v in vectors]
        return [h.keys(v) for h, v in zip(self.hashers, vectors)]

    def observe(self, obs: np.ndarray, act: np.ndarray) -> list[np.ndarray]:
        """Count freshly collected training transitions (and nothing else); each table's
        slots of the rows (`counts_at` prices them later without hashing again)."""
        return [table.increment(keys) for table, keys in zip(self.tables, self.keys(obs, act))]

    @property
    def slot_shapes(self) -> list[tuple[int, ...]]:
        """One row's slot in each table: () for an exact table, (depth,) for a sketch."""
        return [t.slot_shape for t in self.tables]

    def slots(self, obs: np.ndarray, act: np.ndarray) -> list[np.ndarray]:
        """Each table's slots of these rows, counting nothing (a key never counted: a
        slot whose count is 0)."""
        return [t.slots(k) for t, k in zip(self.tables, self.keys(obs, act))]

    def counts_at(self, slots: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Each table's counts now at these slots: `counts` of the rows they are the
        slots of, as a gather (a row's key, so its slot, never changes)."""
        return [t.gather(s) for t, s in zip(self.tables, slots)]

    def counts(self, obs: np.ndarray, act: np.ndarray) -> list[np.ndarray]:
        return [t.counts(k) for t, k in zip(self.tables, self.keys(obs, act))]

    def bonus(self, obs: np.ndarray, act: np.ndarray) -> np.ndarray:
        """Per-agent bonus (B, N) for a sampled batch; computed now, never stored."""
        return self.bonus_from_counts(self.counts(obs, act), len(obs))

    def bonus_from_counts(
        self, counts: list[np.ndarray], batch: int, beta: float | None = None
    ) -> np.ndarray:
        """Spread table counts onto agents: Dis gives each its own, Cen one for all;
        at `beta` (a schedule's value now), else the spec's."""
        return price(
            self.spec.mode, counts, self.spec.beta if beta is None else beta, batch, self.n_agents
        )

    def stats(self) -> dict[str, float]:
        """Table size, count-1 percentage (over all tables' keys) and transitions counted."""
        size = sum(len(t) for t in self.tables)
        c1 = sum(t.count1 for t in self.tables)
        return {
            "table_size": size,
            "count1_pct": 100.0 * c1 / size if size else 0.0,
            "counted_transitions": self.tables[0].total if self.tables else 0,
        }


def price(
    mode: str, counts: Sequence[np.ndarray], beta: float, batch: int, n_agents: int
) -> np.ndarray:
    """The (batch, n_agents) bonus of `mode` at `beta` from each table's (batch,) counts
    (n >= 1): every pricing site's one formula, so the learner service, pricing a
    scheduled beta from the counter's counts, gives the trainer's bits."""
    if mode == "none":
        return np.zeros((batch, n_agents), np.float32)
    if mode == "constant":
        return np.full((batch, n_agents), beta, np.float32)
    per_table = np.stack([count_bonus(c, beta) for c in counts], axis=1)
    if mode == "cen-macb":
        return np.repeat(per_table, n_agents, axis=1)
    return per_table


class BonusDiagnostics:
    """What the bonus did on the rows sampled since the last metric point.

    `bonus_mean` and `bonus_std` over every sampled (row, agent) bonus, and
    `sampled_count1_pct`, the share of sampled (row, table) keys with n = 1. A std of 0
    with a positive mean means the bonus was a constant reward shift on every sampled
    row (every key new, or the `constant` arm): what counting cannot explain. Sums
    only, so recording costs a few numpy reductions per update.
    """

    FIELDS = ("bonus_mean", "bonus_std", "sampled_count1_pct")

    def __init__(self) -> None:
        self._reset()

    def _reset(self) -> None:
        self.n = 0
        self.total = 0.0
        self.total_sq = 0.0
        self.keys = 0
        self.count1 = 0
        self.low = np.inf
        self.high = -np.inf

    def record(self, bonus: np.ndarray, counts: Sequence[np.ndarray] | np.ndarray) -> None:
        """One sampled batch: its (B, N) bonus and each table's (B,) counts (none for
        the arms without tables). A count of 0 (a row the counter had not counted yet)
        was priced as n = 1, and is counted as such."""
        b = np.asarray(bonus, dtype=np.float64)
        self.n += b.size
        self.total += float(b.sum())
        self.total_sq += float(np.square(b).sum())
        if b.size:
            self.low = min(self.low, float(b.min()))
            self.high = max(self.high, float(b.max()))
        for c in counts:
            c = np.asarray(c)
            self.keys += c.size
            self.count1 += int(np.count_nonzero(c <= 1))

    def take(self) -> dict[str, float]:
        """The fields for this point; starts over for the next."""
        mean = self.total / self.n if self.n else 0.0
        var = max(0.0, self.total_sq / self.n - mean * mean) if self.n else 0.0
        # Exactly 0 when every value was the same (sums of squares leave rounding residue).
        std = 0.0 if self.low >= self.high else float(np.sqrt(var))
        out = {
            "bonus_mean": mean,
            "bonus_std": std,
            "sampled_count1_pct": 100.0 * self.count1 / self.keys if self.keys else 0.0,
        }
        self._reset()
        return out


def constant_shift(rows: Sequence[dict], last: int = 2) -> bool:
    """The bonus was a constant reward shift over the last `last` points: std 0 with a
    positive mean at each (at least one point needed)."""
    tail = [r for r in rows[-last:] if "bonus_std" in r]
    return bool(tail) and all(r["bonus_std"] == 0 and r["bonus_mean"] > 0 for r in tail)
