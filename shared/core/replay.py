"""A ring replay buffer of joint transitions (s, x, r, s', done) in preallocated arrays.

It stores the extrinsic reward only: the count bonus depends on the counts at the
time a transition is sampled, so it is added to each sampled batch, never stored
(`bonus_at: collection` aside). What it may store for the bonus is each row's slot in
each count table, so pricing a sampled batch gathers the counts now at its slots.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
import torch

from shared.core.transfer import send


@dataclass
class Batch:
    obs: np.ndarray  # (B, joint_obs_dim) float32
    act: np.ndarray  # (B, joint_act_dim) float32
    rew: np.ndarray  # (B,) float32, extrinsic
    next_obs: np.ndarray  # (B, joint_obs_dim) float32
    done: np.ndarray  # (B,) float32, 1 where the target must not bootstrap
    idx: np.ndarray  # (B,) buffer rows
    bonus: np.ndarray | None = None  # (B, N) the bonus stored at collection, if any


class ReplayBuffer:
    """`stored_bonus` N > 0 keeps a per-agent bonus with each transition (`bonus_at:
    collection`, the thesis code's fig. 3 loop); without it no bonus is stored.

    `slot_shapes` (one per count table) keeps each row's slot in each table, given when
    it was counted (`CountExploration.observe`): its bonus at sample time is then a
    gather of the counts at its slots rather than a hash of its key. `store` gives the
    arrays to write in (a `GroupReplay`'s rows of one run) instead of new ones; `sink`
    takes each added batch's rows and fields instead of host arrays (a `GroupReplay`
    whose rows live on a device: the buffer keeps its position, count and slots only,
    and its rows are read by the group's gather, not by `take`)."""

    obs: np.ndarray
    act: np.ndarray
    rew: np.ndarray
    next_obs: np.ndarray
    done: np.ndarray

    def __init__(
        self,
        capacity: int,
        obs_dim: int,
        act_dim: int,
        stored_bonus: int = 0,
        slot_shapes: Sequence[tuple[int, ...]] = (),
        store: dict[str, np.ndarray] | None = None,
        sink: Callable[[np.ndarray, dict[str, Any]], None] | None = None,
    ) -> None:
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self.capacity = capacity
        fields = replay_fields(obs_dim, act_dim, stored_bonus, slot_shapes)
        if store is None:
            store = {name: np.zeros((capacity, *shape), dt) for name, (shape, dt) in fields.items()}
        self.sink = sink
        self.stores_bonus = bool(stored_bonus)
        self.bonus: np.ndarray | None = None
        if sink is None:
            self.bonus = store["bonus"] if stored_bonus else None
            self.obs = store["obs"]
            self.act = store["act"]
            self.rew = store["rew"]
            self.next_obs = store["next_obs"]
            self.done = store["done"]
        self.slots = [store[f"slots{t}"] for t in range(len(slot_shapes))]
        self.pos = 0  # next row to write
        self.added = 0  # transitions ever added

    def __len__(self) -> int:
        return min(self.added, self.capacity)

    def add(
        self,
        obs: np.ndarray,
        act: np.ndarray,
        rew: np.ndarray | float,
        next_obs: np.ndarray,
        done: np.ndarray | float,
        bonus: np.ndarray | None = None,
        slots: Sequence[np.ndarray] = (),
    ) -> None:
        """Add one transition or a batch of them (leading axis = transitions); `bonus`
        (N,) or (n, N) where the buffer stores bonuses; `slots` each table's (n, ...)
        where it stores slots."""
        obs = np.atleast_2d(obs)
        n = len(obs)
        rows = (self.pos + np.arange(n)) % self.capacity
        if self.stores_bonus and bonus is None:
            raise ValueError("this buffer stores a bonus with every transition")
        if len(slots) != len(self.slots):
            raise ValueError(
                f"this buffer stores {len(self.slots)} slots a row, given {len(slots)}"
            )
        for store, s in zip(self.slots, slots):
            store[rows] = s
        if self.sink is not None:
            fields: dict[str, Any] = {"obs": obs, "act": act, "rew": rew,
                                         "next_obs": next_obs, "done": done}  # fmt: skip
            if self.stores_bonus:
                fields["bonus"] = bonus
            self.sink(rows, fields)
        else:
            if self.bonus is not None and bonus is not None:
                self.bonus[rows] = np.atleast_2d(bonus)
            self.obs[rows] = obs
            self.act[rows] = np.atleast_2d(act)
            self.rew[rows] = rew
            self.next_obs[rows] = np.atleast_2d(next_obs)
            self.done[rows] = done
        self.pos = int((self.pos + n) % self.capacity)
        self.added += n

    def draw(self, batch_size: int, rng: np.random.Generator) -> np.ndarray:
        """A minibatch's rows: uniform with replacement, as SB3 and the thesis code do."""
        size = len(self)
        if size == 0:
            raise ValueError("cannot sample from an empty buffer")
        return rng.integers(0, size, size=batch_size)

    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        """Uniform sample with replacement (`draw`'s rows)."""
        return self.take(self.draw(batch_size, rng))

    def take(self, idx: np.ndarray) -> Batch:
        """The rows `idx`, from host arrays (a buffer whose rows live on a device has none)."""
        if self.sink is not None:
            raise ValueError(
                "this buffer's rows live on a device: read them with its group's gather"
            )
        bonus = None if self.bonus is None else self.bonus[idx]
        return Batch(
            self.obs[idx], self.act[idx], self.rew[idx], self.next_obs[idx], self.done[idx], idx,
            bonus,
        )  # fmt: skip


def replay_fields(
    obs_dim: int, act_dim: int, stored_bonus: int, slot_shapes: Sequence[tuple[int, ...]]
) -> dict[str, tuple[tuple[int, ...], type]]:
    """Each stored field's row shape and dtype."""
    fields: dict[str, tuple[tuple[int, ...], type]] = {
        "obs": ((obs_dim,), np.float32),
        "act": ((act_dim,), np.float32),
        "rew": ((), np.float32),
        "next_obs": ((obs_dim,), np.float32),
        "done": ((), np.float32),
    }
    if stored_bonus:
        fields["bonus"] = ((stored_bonus,), np.float32)
    for t, shape in enumerate(slot_shapes):
        fields[f"slots{t}"] = (tuple(shape), np.int32)
    return fields


class GroupReplay:
    """R runs' replay buffers as one array per field, (R, capacity, ...): run r's
    `ReplayBuffer` (`buffers[r]`, its own capacity, position and slots) writes its rows
    there, and one gather takes every run's minibatches at once.

    Each run's rows are drawn from its own generator in its order (`draw`), so they are
    the rows it draws alone; only the copying out is shared. Slots stay per run (runs of
    a group may count in different tables, or none) and on the host, with the counts.

    On a `device` other than the CPU the fields are tensors there (backend "torch"): a
    run's `add` leaves its rows pending, `flush` writes every pending row in one copy,
    and `gather_on_device` takes the rows as a tensor there (`send`). The draws stay on
    the host, each run's from its own generator, so the rows gathered are those the host
    gathers. `backend` "torch" on the CPU runs that path with CPU tensors (what the
    CPU's tests check it by); the CPU's default, "numpy", is the host arrays above."""

    def __init__(
        self,
        capacities: Sequence[int],
        obs_dim: int,
        act_dim: int,
        stored_bonus: Sequence[int],
        slot_shapes: Sequence[Sequence[tuple[int, ...]]],
        device: str | torch.device = "cpu",
        backend: str | None = None,
    ) -> None:
        self.runs = runs = len(capacities)
        self.capacity = cap = max(capacities)
        self.device = torch.device(device)
        self.backend = backend or ("numpy" if self.device.type == "cpu" else "torch")
        if self.backend not in ("numpy", "torch"):
            raise ValueError(f"replay backend must be numpy or torch, got {self.backend!r}")
        if self.backend == "numpy" and self.device.type != "cpu":
            raise ValueError(f"a numpy replay lives on the CPU, not {self.device}")
        width = max(stored_bonus)
        shared = replay_fields(obs_dim, act_dim, width, ())
        self.row_shapes = {k: shape for k, (shape, _) in shared.items()}
        self.arrays: dict[str, np.ndarray] = {}
        self.tensors: dict[str, torch.Tensor] = {}
        # Rows added since the last `flush` (torch): each batch's flat rows and fields.
        self.pending: list[tuple[np.ndarray, dict[str, Any]]] = []
        if self.backend == "numpy":
            self.arrays = {
                k: np.zeros((runs, cap, *shape), dt) for k, (shape, dt) in shared.items()
            }
        else:
            self.tensors = {
                k: torch.zeros((runs * cap, *shape), dtype=torch.float32, device=self.device)
                for k, shape in self.row_shapes.items()
            }
            self.base = torch.arange(runs, device=self.device).view(-1, 1, 1) * cap
        self.buffers: list[ReplayBuffer] = []
        for r, (c, sb, shapes) in enumerate(zip(capacities, stored_bonus, slot_shapes)):
            store = {k: v[r, :c] for k, v in self.arrays.items()}
            for t, shape in enumerate(shapes):
                store[f"slots{t}"] = np.zeros((c, *shape), np.int32)
            sink = None if self.backend == "numpy" else partial(self.add_rows, r)
            self.buffers.append(ReplayBuffer(c, obs_dim, act_dim, sb, shapes, store, sink))

    def add_rows(self, run: int, rows: np.ndarray, fields: dict[str, Any]) -> None:
        """Run `run`'s rows added (torch): kept for the next `flush`, as copies (the
        caller's arrays may be its own to write again)."""
        kept = {k: np.array(v, np.float32) for k, v in fields.items() if v is not None}
        self.pending.append((rows + run * self.capacity, kept))

    def flush(self) -> None:
        """Every pending row onto the device in one copy (`send`), then written in one
        indexed copy per field. A row added twice since the last flush keeps its last
        value, as writing in order would (the device's indexed copy has no order)."""
        if not self.pending:
            return
        rows = np.concatenate([r for r, _ in self.pending])
        n = len(rows)
        data = {k: np.zeros((n, *shape), np.float32) for k, shape in self.row_shapes.items()}
        at = 0
        for r, fields in self.pending:
            for k, v in fields.items():
                data[k][at : at + len(r)] = v
            at += len(r)
        self.pending = []
        _, last = np.unique(rows[::-1], return_index=True)
        if len(last) < n:  # duplicates: keep each row's last write
            keep = np.sort(n - 1 - last)
            rows, data = rows[keep], {k: v[keep] for k, v in data.items()}
        names = list(data)
        sent = send([rows.astype(np.int64), *(data[k] for k in names)], self.device)
        for k, v in zip(names, sent[1:]):
            self.tensors[k].index_copy_(0, sent[0], v)

    def draw(
        self, batch_size: int, count: int, rngs: Sequence[np.random.Generator | None]
    ) -> np.ndarray:
        """(R, count, batch_size) rows: run r's `count` minibatches from `rngs[r]`, in
        order (row 0 for a run given None, drawing nothing)."""
        idx = np.zeros((self.runs, count, batch_size), np.int64)
        for r, (buffer, rng) in enumerate(zip(self.buffers, rngs)):
            if rng is not None:
                for j in range(count):
                    idx[r, j] = buffer.draw(batch_size, rng)
        return idx

    def gather(self, idx: np.ndarray) -> dict[str, np.ndarray]:
        """Every field at rows `idx` (R, ...) of each run: (R, ..., field's row shape)."""
        flat = idx + self.capacity * np.arange(self.runs).reshape(-1, *[1] * (idx.ndim - 1))
        flat = flat.reshape(-1)
        out = {}
        for k, v in self.arrays.items():
            rows = v.reshape(self.runs * self.capacity, *v.shape[2:]).take(flat, axis=0)
            out[k] = rows.reshape(*idx.shape, *v.shape[2:])
        return out

    def gather_on_device(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        """`gather` on the device (torch): `idx` (R, k, B) a tensor there (`send`); the
        rows pending are written first."""
        self.flush()
        flat = (idx + self.base).reshape(-1)
        return {
            k: v.index_select(0, flat).view(*idx.shape, *self.row_shapes[k])
            for k, v in self.tensors.items()
        }


def update_arrays(
    batches: list[Batch], bonuses: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What a learner's `update` takes for one update: (obs, act, rew, next_obs, done) of
    one shared minibatch with its reward plus bonus (rew (B, N)), or, given one
    minibatch per agent, the same stacked with a leading agent axis (rew (N, B, N))."""
    rews = [b.rew[:, None] + bonus for b, bonus in zip(batches, bonuses, strict=True)]
    if len(batches) == 1:
        b = batches[0]
        return b.obs, b.act, rews[0], b.next_obs, b.done
    return (
        np.stack([b.obs for b in batches]),
        np.stack([b.act for b in batches]),
        np.stack(rews),
        np.stack([b.next_obs for b in batches]),
        np.stack([b.done for b in batches]),
    )


def fixed_update_arrays(
    buffer: ReplayBuffer, batch_size: int, per_update: int, n_agents: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The update arrays of a group's run that its `early_stop` rule ended: one fixed
    draw of `per_update` minibatches from its replay (a sampler of its own, so the
    run's stream is untouched), no bonus. Its stack entry keeps running on them, so the
    group's update keeps its shape, while the entries do not mix: the other runs' rows
    stay what they give alone. One definition for the trainer and the learner service."""
    batches = [buffer.take(idx) for idx in fixed_draws(buffer, batch_size, per_update)]
    zero = [np.zeros((len(b.rew), n_agents), np.float32) for b in batches]
    return update_arrays(batches, zero)


def fixed_draws(buffer: ReplayBuffer, batch_size: int, per_update: int) -> np.ndarray:
    """The rows (per_update, batch_size) of `fixed_update_arrays`' draw, from a sampler
    of its own: the one-process group gathers them with its other runs' rows."""
    rng = np.random.default_rng(0)
    return np.stack([buffer.draw(batch_size, rng) for _ in range(per_update)])
