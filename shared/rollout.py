"""Collecting training transitions and running noise-free evaluation episodes.

The same code serves the one-process trainer and the actor service: a `Collector`
steps one environment with exploration noise and yields joint transitions; the
`evaluate` function runs evaluation episodes in lockstep so that one batched
forward pass serves all of them. Neither ever touches a count table.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from shared.tasks import TaskEnv

Policy = Callable[[np.ndarray], np.ndarray]  # joint obs (B, O) -> joint actions (B, A)


def derive_seed(seed: int, role: str, rank: int = 0) -> int:
    """A stable 32-bit seed for (run seed, role, rank): actors, evaluators and samplers differ."""
    entropy = [seed, zlib.crc32(role.encode()), rank]
    return int(np.random.SeedSequence(entropy).generate_state(1)[0])


@dataclass
class Transition:
    obs: np.ndarray  # (joint_obs,)
    act: np.ndarray  # (joint_act,)
    rew: float  # extrinsic
    next_obs: np.ndarray
    done: float  # 1.0 only when the time limit is treated as terminal
    success: bool
    collisions: int
    episode_end: bool


class Collector:
    """Steps one env with Gaussian action noise (sigma relative to each dim's half-range)."""

    def __init__(
        self, env: TaskEnv, noise_sigma: float, seed: int, time_limit_terminal: bool = False
    ) -> None:
        self.env = env
        spec = env.spec
        self.low = np.concatenate([np.asarray(a.act_low, np.float32) for a in spec.agents])
        self.high = np.concatenate([np.asarray(a.act_high, np.float32) for a in spec.agents])
        self.noise_scale = noise_sigma * (self.high - self.low) / 2
        self.rng = np.random.default_rng(seed)
        self.time_limit_terminal = time_limit_terminal
        self.obs = np.concatenate(env.reset(seed=seed))
        self.episodes = 0
        self.episode_return = 0.0

    def noisy(self, act: np.ndarray) -> np.ndarray:
        noise = self.rng.standard_normal(act.shape).astype(np.float32) * self.noise_scale
        return np.clip(act + noise, self.low, self.high)

    def step(self, policy: Policy) -> Transition:
        obs = self.obs
        act = self.noisy(policy(obs[None])[0])
        res = self.env.step_joint(act)
        next_obs = res.obs
        self.episode_return += res.reward
        done = 1.0 if (res.truncated and self.time_limit_terminal) else 0.0
        tr = Transition(
            obs, act, res.reward, next_obs, done, res.success, res.collisions, res.truncated
        )
        if res.truncated:
            self.episodes += 1
            self.episode_return = 0.0
            self.obs = np.concatenate(self.env.reset())
        else:
            self.obs = next_obs
        return tr


@dataclass
class EvalResult:
    success_rate: float  # share of episodes in which the task condition held at some step
    eval_return: float  # mean extrinsic episode return
    episodes: int
    steps: int


def evaluate(policy: Policy, envs: list[TaskEnv], episodes: int) -> EvalResult:
    """Noise-free episodes, len(envs) at a time in lockstep; counts are never touched."""
    successes, returns, steps = [], [], 0
    remaining = episodes
    while remaining > 0:
        group = envs[: min(len(envs), remaining)]
        obs = np.stack([np.concatenate(e.reset()) for e in group])
        ok = np.zeros(len(group), bool)
        ret = np.zeros(len(group))
        done = False
        while not done:
            acts = policy(obs)
            for j, env in enumerate(group):
                res = env.step_joint(acts[j])
                obs[j] = res.obs
                ok[j] |= res.success
                ret[j] += res.reward
                done = res.truncated
            steps += len(group)
        successes += ok.tolist()
        returns += ret.tolist()
        remaining -= len(group)
    return EvalResult(float(np.mean(successes)), float(np.mean(returns)), episodes, steps)
