"""Collecting training transitions and running noise-free evaluation episodes.

The same code serves the one-process trainer and the actor service: a `Collector`
steps one environment with exploration noise and yields joint transitions; the
`evaluate` function runs evaluation episodes in lockstep so that one batched
forward pass serves all of them. Neither ever touches a count table. Both honour
the env's `success_terminal` (a success step is terminal and the episode goes on in
a new world), and `make_collector` builds an actor's collector from the run config.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from shared.envs.tasks import TaskEnv

if TYPE_CHECKING:
    from shared.config import TrainConfig

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
    next_obs: np.ndarray  # at a terminal success, the world before its reset
    done: float  # 1.0 at a terminal success, or at the time limit when it is terminal
    success: bool
    collisions: int
    episode_end: bool  # the episode's time limit (not a success: the episode goes on)


class Collector:
    """Steps one env with Gaussian action noise (sigma relative to each dim's half-range).

    Its first `warmup_steps` actions are drawn uniformly from each agent's action box
    instead of asking the policy, then noised like the policy's (the thesis code's
    warm-up, `maddpg_countbased.py:198-202,219-223`: `action_space.sample()` goes
    through the same noise and clipping). After a terminal success step (the env's
    `success_terminal`) the next step starts from a new world, inside the same episode.
    """

    def __init__(
        self,
        env: TaskEnv,
        noise_sigma: float,
        seed: int,
        time_limit_terminal: bool = False,
        warmup_steps: int = 0,
    ) -> None:
        self.env = env
        spec = env.spec
        self.low = np.concatenate([np.asarray(a.act_low, np.float32) for a in spec.agents])
        self.high = np.concatenate([np.asarray(a.act_high, np.float32) for a in spec.agents])
        self.noise_scale = noise_sigma * (self.high - self.low) / 2
        self.rng = np.random.default_rng(seed)
        self.time_limit_terminal = time_limit_terminal
        self.warmup_steps = warmup_steps
        self.obs = np.concatenate(env.reset(seed=seed))
        # The next episode's reset waits for its first step: at an episode boundary the
        # collector's whole state is its counters and RNG states (`state`), which is what
        # a resumed run restores. (The env's RNG is touched by nothing in between, so the
        # episodes are the ones an eager reset gives.)
        self.reset_due = False
        self.steps = 0  # transitions collected
        self.episodes = 0
        self.episode_return = 0.0

    def noisy(self, act: np.ndarray) -> np.ndarray:
        noise = self.rng.standard_normal(act.shape).astype(np.float32) * self.noise_scale
        return np.clip(act + noise, self.low, self.high)

    def random_action(self) -> np.ndarray:
        """Uniform in every agent's action box (float32, as the policy's actions)."""
        return self.rng.uniform(self.low, self.high).astype(np.float32)

    def next_obs(self) -> np.ndarray:
        """The joint observation the next step acts on. A reset due at an episode's end
        happens now rather than in `step` (nothing touches the env's RNG in between, so
        the world is the same): lockstep actors send it to the learner for the action."""
        if self.reset_due:
            self.obs = np.concatenate(self.env.reset())
            self.reset_due = False
        return self.obs

    def step(self, policy: Policy) -> Transition:
        obs = self.next_obs()
        if self.steps < self.warmup_steps:
            act = self.noisy(self.random_action())
        else:
            act = self.noisy(policy(obs[None])[0])
        res = self.env.step_joint(act)
        next_obs = res.obs
        self.steps += 1
        self.episode_return += res.reward
        # An env's own early time limit (`restart`, custom tasks) is a time limit too.
        limit = res.truncated or res.restart
        done = 1.0 if res.terminated or (limit and self.time_limit_terminal) else 0.0
        tr = Transition(
            obs, act, res.reward, next_obs, done, res.success, res.collisions, res.truncated
        )
        if res.truncated:
            self.episodes += 1
            self.episode_return = 0.0
            self.reset_due = True
        elif res.terminated or res.restart:
            self.obs = np.concatenate(self.env.reset_world())
        else:
            self.obs = next_obs
        return tr

    def state(self) -> dict[str, Any]:
        """Counters and RNG states (JSON-able), at an episode boundary only."""
        if not self.reset_due:
            raise RuntimeError("a collector's state is saved between episodes only")
        return {
            "rng": dict(self.rng.bit_generator.state),
            "env_rng": self.env.rng_state(),
            "steps": self.steps,
            "episodes": self.episodes,
        }

    def load_state(self, state: dict[str, Any]) -> None:
        self.rng.bit_generator.state = state["rng"]
        self.env.set_rng_state(state["env_rng"])
        self.steps, self.episodes = int(state["steps"]), int(state["episodes"])
        self.episode_return = 0.0
        self.reset_due = True


def warmup_share(learning_starts: int, actors: int) -> int:
    """Random-action steps of each of `actors` actors: its own first ceil(L / R) steps,
    i.e. while its own collected count times R is below L = learning_starts. With one
    actor (macb train) exactly the run's first L transitions; with R actors about L in
    all (at most R - 1 more), whatever order the learner ingests them in."""
    return -(-learning_starts // actors)


def make_collector(
    cfg: TrainConfig, env: TaskEnv, rank: int = 0, actors: int = 1, steps_done: int = 0
) -> Collector:
    """Actor `rank` of `actors`'s collector for a run: noise, seed, terminal time limit and
    warm-up from the config, so `macb train` and the actor service collect alike.

    `steps_done` > 0: an actor rejoining its run after a restart, `steps_done` of its
    transitions already taken. It draws from a seed of its own for that position (not
    the first episodes' randomness again) and owes only the rest of its warm-up."""
    warmup = warmup_share(cfg.learning_starts, actors) if cfg.warmup == "random" else 0
    seed = derive_seed(cfg.seed, "actor", rank)
    if steps_done:
        seed = derive_seed(seed, "actor-resumed", steps_done)
    return Collector(
        env,
        cfg.noise_sigma,
        seed,
        cfg.time_limit_terminal,
        warmup_steps=max(0, warmup - steps_done),
    )


def make_vec_collector(cfgs: Sequence[TrainConfig], venv: Any, steps_done: int = 0) -> VecCollector:
    """A group's collector (world r is run r's): each run's noise, seed, terminal time
    limit and warm-up as `make_collector` gives it alone (`steps_done` too: a group's
    actor rejoining after a restart), so the group trainer and a group's actor service
    collect alike."""
    seeds = [derive_seed(cfg.seed, "actor", 0) for cfg in cfgs]
    if steps_done:
        seeds = [derive_seed(seed, "actor-resumed", steps_done) for seed in seeds]
    warmups = [warmup_share(c.learning_starts, 1) if c.warmup == "random" else 0 for c in cfgs]
    return VecCollector(
        venv,
        [cfg.noise_sigma for cfg in cfgs],
        seeds,
        [cfg.time_limit_terminal for cfg in cfgs],
        [max(0, w - steps_done) for w in warmups],
    )


@dataclass
class EvalResult:
    success_rate: float  # share of episodes in which the task condition held at some step
    eval_return: float  # mean extrinsic episode return
    episodes: int
    steps: int


def evaluate(policy: Policy, envs: list[TaskEnv], episodes: int) -> EvalResult:
    """Noise-free episodes, len(envs) at a time in lockstep; counts are never touched.

    An episode succeeds when `success` held at some step. With `success_terminal` a
    success resets the world and the episode runs on to its time limit, so the return
    also sums the rewards of the new world. The thesis code's evaluation did not reset
    (it stepped the raw MultiAgentEnv, which never resets; only training's vec-env
    wrapper does): the success rate is the same either way, the return is not
    comparable with the code's (docs/fidelity.md, E2)."""
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
                # A terminal success goes on in a new world (the code's evaluation went
                # on in the old one); success was seen, so the rate is the same.
                ended = (res.terminated or res.restart) and not res.truncated
                obs[j] = np.concatenate(env.reset_world()) if ended else res.obs
                ok[j] |= res.success
                ret[j] += res.reward
                done = res.truncated
            steps += len(group)
        successes += ok.tolist()
        returns += ret.tolist()
        remaining -= len(group)
    return EvalResult(float(np.mean(successes)), float(np.mean(returns)), episodes, steps)


# ---------------------------------------------------------------------- run groups
GroupPolicy = Callable[[np.ndarray], np.ndarray]  # (R, rows, joint_obs) -> (R, rows, joint_act)


class WorldError(RuntimeError):
    """A step gave a non-finite observation or reward (a custom task's bug) or action (a
    learner gone to NaN): it would go into replay and every update after it, so the run
    ends saying where, in `macb train` as in the cluster (whose actor refuses to send
    such rows)."""


def nonfinite(tr: VecTransitions, runs: Sequence[str]) -> str | None:
    """Where a step of R worlds holds a value that is not finite (None: nowhere)."""
    for field in ("obs", "act", "rew", "next_obs"):
        ok = np.isfinite(getattr(tr, field)).reshape(len(runs), -1).all(axis=1)
        if not ok.all():
            run = runs[int(np.argmin(ok))]
            if field == "act":  # (from the policy: its learner's weights are not finite)
                return f"run {run}: its policy gave a non-finite action (a diverged learner)"
            return f"run {run}: its world gave a non-finite {field}"
    return None


@dataclass
class VecTransitions:
    """One step of R runs' collectors: (R, ...) arrays, row r what run r's `Collector`
    would have given as its `Transition`."""

    obs: np.ndarray
    act: np.ndarray
    rew: np.ndarray
    next_obs: np.ndarray
    done: np.ndarray
    success: np.ndarray
    collisions: np.ndarray
    episode_end: np.ndarray


class VecCollector:
    """R runs' `Collector`s over one world each of a VecTask (world r is run r's).

    Run r draws its noise, warm-up actions and worlds from run r's streams exactly as
    its `Collector` alone does (same seed, same order of draws; noise and worlds one
    stream: docs/fidelity.md, L7), so its transitions are
    the same; the policy is asked once per step for every run. Episodes of a group end
    together (one `episode_len`), so a cut's episode boundary is every run's."""

    def __init__(
        self,
        venv: Any,
        noise_sigmas: list[float],
        seeds: list[int],
        time_limit_terminal: list[bool],
        warmup_steps: list[int],
    ) -> None:
        self.venv = venv
        self.runs = r = venv.e
        spec = venv.spec
        self.low = np.concatenate([np.asarray(a.act_low, np.float32) for a in spec.agents])
        self.high = np.concatenate([np.asarray(a.act_high, np.float32) for a in spec.agents])
        self.noise_scale = [s * (self.high - self.low) / 2 for s in noise_sigmas]
        self.rngs = [np.random.default_rng(seed) for seed in seeds]
        self.time_limit_terminal = np.array(time_limit_terminal)
        self.warmup_steps = list(warmup_steps)
        self.obs = np.stack([venv.reset(i, seed=seed) for i, seed in enumerate(seeds)])
        self.reset_due = np.zeros(r, bool)
        self.steps = 0  # transitions collected by each run
        self.episodes = 0

    def _noisy(self, r: int, act: np.ndarray) -> np.ndarray:
        rng = self.rngs[r]
        noise = rng.standard_normal(act.shape).astype(np.float32) * self.noise_scale[r]
        return np.clip(act + noise, self.low, self.high)

    def next_obs(self) -> np.ndarray:
        """Every run's joint observation the next step acts on, (R, joint_obs): the
        resets due at an episode's end happen now rather than in `step` (as
        `Collector.next_obs`, for a lockstep actor serving a group)."""
        for r in np.nonzero(self.reset_due)[0]:
            self.obs[r] = self.venv.reset(int(r))
        self.reset_due[:] = False
        return self.obs.copy()

    def step(self, policy: GroupPolicy) -> VecTransitions:
        venv = self.venv
        obs = self.next_obs()
        warm = [self.steps < w for w in self.warmup_steps]
        policy_act = None if all(warm) else policy(obs[:, None])[:, 0]
        act = np.empty((self.runs, len(self.low)), np.float32)
        for r in range(self.runs):
            if warm[r]:
                a = self.rngs[r].uniform(self.low, self.high).astype(np.float32)
            else:
                assert policy_act is not None  # some run is past its warmup
                a = policy_act[r]
            act[r] = self._noisy(r, a)
        res = venv.step(act)
        self.steps += 1
        limit = res.truncated | res.restart
        done = (res.terminated | (limit & self.time_limit_terminal)).astype(np.float32)
        tr = VecTransitions(
            obs, act, res.reward, res.obs, done, res.success, res.collisions, res.truncated
        )
        for r in range(self.runs):
            if res.truncated[r]:
                self.reset_due[r] = True
            elif res.terminated[r] or res.restart[r]:
                self.obs[r] = venv.reset_world(r)
            else:
                self.obs[r] = res.obs[r]
        if res.truncated.all():
            self.episodes += 1
        return tr

    def state(self, r: int) -> dict[str, Any]:
        """Run r's collector state, in `Collector.state`'s format (between episodes)."""
        if not self.reset_due[r]:
            raise RuntimeError("a collector's state is saved between episodes only")
        return {
            "rng": dict(self.rngs[r].bit_generator.state),
            "env_rng": self.venv.rng_state(r),
            "steps": self.steps,
            "episodes": self.episodes,
        }

    def load_state(self, states: list[dict[str, Any]]) -> None:
        """Every run's state (`Collector.state`'s format; the runs are at one step)."""
        steps = {int(s["steps"]) for s in states}
        if len(steps) != 1:
            raise ValueError(f"the runs' collectors are at different steps: {sorted(steps)}")
        for r, s in enumerate(states):
            self.rngs[r].bit_generator.state = s["rng"]
            self.venv.set_rng_state(r, s["env_rng"])
        self.steps = steps.pop()
        self.episodes = int(states[0]["episodes"])
        self.reset_due[:] = True


def evaluate_group(policy: GroupPolicy, venv: Any, runs: int, episodes: int) -> list[EvalResult]:
    """`evaluate` for R runs at once: `venv` holds m worlds per run (run r's are worlds
    r*m .. r*m+m-1, each its lone evaluation env), stepped together; one policy call per
    step serves every run's episodes. Run r's result is what `evaluate` gives it."""
    from shared.envs.vectask import vectorize

    m = venv.e // runs
    successes: list[list[bool]] = [[] for _ in range(runs)]
    returns: list[list[float]] = [[] for _ in range(runs)]
    steps, remaining = 0, episodes
    while remaining > 0:
        k = min(m, remaining)
        w = (
            venv
            if k == m
            else vectorize([venv.envs[r * m + j] for r in range(runs) for j in range(k)])
        )
        obs = np.stack([w.reset(i) for i in range(w.e)])
        ok = np.zeros(w.e, bool)
        ret = np.zeros(w.e)
        done = False
        while not done:
            acts = policy(obs.reshape(runs, k, -1)).reshape(w.e, -1)
            res = w.step(acts)
            ended = (res.terminated | res.restart) & ~res.truncated
            obs = res.obs.copy()
            for i in np.nonzero(ended)[0]:
                obs[i] = w.reset_world(int(i))
            ok |= res.success
            ret += res.reward
            done = bool(res.truncated[-1])
            steps += k
        for r in range(runs):
            successes[r] += ok[r * k : (r + 1) * k].tolist()
            returns[r] += ret[r * k : (r + 1) * k].tolist()
        remaining -= k
    return [
        EvalResult(float(np.mean(s)), float(np.mean(rt)), episodes, steps)
        for s, rt in zip(successes, returns)
    ]
