"""A ring replay buffer of joint transitions (s, x, r, s', done) in preallocated arrays.

It stores the extrinsic reward only: the count bonus depends on the counts at the
time a transition is sampled, so it is added to each sampled batch, never stored.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
    collection`, the thesis code's fig. 3 loop); without it no bonus is stored."""

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, stored_bonus: int = 0) -> None:
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self.capacity = capacity
        self.bonus = np.zeros((capacity, stored_bonus), np.float32) if stored_bonus else None
        self.obs = np.zeros((capacity, obs_dim), np.float32)
        self.act = np.zeros((capacity, act_dim), np.float32)
        self.rew = np.zeros(capacity, np.float32)
        self.next_obs = np.zeros((capacity, obs_dim), np.float32)
        self.done = np.zeros(capacity, np.float32)
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
    ) -> None:
        """Add one transition or a batch of them (leading axis = transitions); `bonus`
        (N,) or (n, N) where the buffer stores bonuses."""
        obs = np.atleast_2d(obs)
        n = len(obs)
        rows = (self.pos + np.arange(n)) % self.capacity
        if self.bonus is not None:
            if bonus is None:
                raise ValueError("this buffer stores a bonus with every transition")
            self.bonus[rows] = np.atleast_2d(bonus)
        self.obs[rows] = obs
        self.act[rows] = np.atleast_2d(act)
        self.rew[rows] = rew
        self.next_obs[rows] = np.atleast_2d(next_obs)
        self.done[rows] = done
        self.pos = int((self.pos + n) % self.capacity)
        self.added += n

    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        """Uniform sample with replacement, as SB3 and the thesis code do."""
        size = len(self)
        if size == 0:
            raise ValueError("cannot sample from an empty buffer")
        idx = rng.integers(0, size, size=batch_size)
        bonus = None if self.bonus is None else self.bonus[idx]
        return Batch(
            self.obs[idx], self.act[idx], self.rew[idx], self.next_obs[idx], self.done[idx], idx,
            bonus,
        )  # fmt: skip


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
    rng = np.random.default_rng(0)
    batches = [buffer.sample(batch_size, rng) for _ in range(per_update)]
    zero = [np.zeros((len(b.rew), n_agents), np.float32) for b in batches]
    return update_arrays(batches, zero)
