"""E worlds of one built-in task stepped as arrays: what a run group collects and
evaluates with.

Every world is a `TaskEnv` (shared/envs/tasks.py) for what happens rarely and draws from its
RNG: `reset` and `reset_world` go to that world's own mpe2 env, so world i draws its
worlds from its own stream exactly as a lone `TaskEnv` with the same seed does, and
`rng_state` is that env's. What happens every step (mpe2's physics, the observations,
the sparse and dense rewards, success and collisions) runs here on (E, entities, 2)
float64 arrays, one numpy operation for all E worlds, in mpe2's own arithmetic order
(`World.step`: action forces, pairwise contact forces added in mpe2's order, then the
chosen integrator; `Scenario.observation`; the adapter's `evaluate`). tests/test_vectask.py
steps both side by side and asserts equal observations, rewards and flags.

Only the three built-in tasks are vectorized; a custom PettingZoo task is stepped world
by world behind the same interface (`ListTask`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from shared.envs.tasks import SPARSE_OFFSET, TaskEnv, is_custom


class VecStep(NamedTuple):
    """One step of E worlds: (E, joint_obs) float32 observations and (E,) flags, each
    meaning what `JointStep`'s field of the same name means for one world."""

    obs: np.ndarray
    reward: np.ndarray  # float64
    success: np.ndarray  # bool
    collisions: np.ndarray  # int64
    truncated: np.ndarray  # bool
    terminated: np.ndarray  # bool
    restart: np.ndarray  # bool (custom tasks only)


class VecTask:
    """E `TaskEnv`s of the same built-in task and options, stepped as arrays.

    `step` steps every world; `reset(i)` and `reset_world(i)` start world i anew (through
    its own env, whose RNG they use), `rng_state(i)` / `set_rng_state(i, s)` save and
    restore its RNG as `TaskEnv`'s do."""

    def __init__(self, envs: Sequence[TaskEnv]) -> None:
        if not envs:
            raise ValueError("a VecTask needs at least one world")
        first = envs[0]
        if is_custom(first.task if hasattr(first, "task") else ":"):
            raise ValueError("custom tasks are stepped world by world (ListTask)")
        for other in envs[1:]:
            if _signature(other) != _signature(first):
                raise ValueError("every world of a VecTask must be the same task and options")
        self.envs = list(envs)
        self.e = len(envs)
        self.spec = spec = first.spec
        self.task = first.task
        # The reward may differ from world to world (a group's sparse and dense arms).
        self.reward_kinds = np.array([e.reward_kind for e in envs])
        self.any_dense = bool((self.reward_kinds == "dense").any())
        self.success_terminal = first.success_terminal
        self.landmark_cover = first._landmark_cover
        self.velocity_first = first._velocity_first
        world = first.world
        self.n_agents = len(world.agents)
        self.n_landmarks = len(world.landmarks)
        entities = world.agents + world.landmarks
        self.dt, self.damping = float(world.dt), float(world.damping)
        self.contact_force, self.contact_margin = world.contact_force, world.contact_margin
        self.dim_c = world.dim_c
        self.movable = np.array([en.movable for en in entities])
        self.mass = np.array([en.mass for en in entities], np.float64)
        if any(en.max_speed is not None for en in entities):
            raise ValueError("max_speed is not vectorized (no built-in task sets it)")
        self.accel = np.array(
            [5.0 if a.accel is None else a.accel for a in world.agents], np.float64
        )
        self.silent = [a.silent for a in world.agents]
        self.colliders = [i for i, en in enumerate(entities) if en.collide]
        self.agent_colliders = [i for i, a in enumerate(world.agents) if a.collide]
        self.local_ratio = first._raw.local_ratio
        self.low, self.high = first._low, first._high
        self.keep = list(first._keep)
        self.obs_off = np.cumsum([0, *spec.obs_dims])
        self.act_off = np.cumsum([0, *spec.act_dims])
        self.move_dims = [a.move_dim for a in spec.agents]
        e, n_ent = self.e, len(entities)
        self.pos = np.zeros((e, n_ent, 2))
        self.vel = np.zeros((e, n_ent, 2))
        self.comm = np.zeros((e, self.n_agents, self.dim_c))
        self.size = np.zeros((e, n_ent))
        self.goal = np.zeros(e, np.int64)  # speaker_listener: the goal landmark
        self.colour = np.zeros((e, self.n_landmarks, world.dim_color))
        self.t = np.full(e, -1, np.int64)  # steps this episode; -1 until reset
        self.ended = np.zeros(e, bool)  # success ended this world: reset_world first

    # ------------------------------------------------------------------ worlds
    def _load(self, i: int) -> np.ndarray:
        """World i's state read from its env (just reset), and its observation."""
        world = self.envs[i].world
        for j, en in enumerate(world.agents + world.landmarks):
            self.pos[i, j] = en.state.p_pos
            self.vel[i, j] = en.state.p_vel
            self.size[i, j] = en.size
        for j, a in enumerate(world.agents):
            self.comm[i, j] = a.state.c if a.state.c is not None else 0.0
        for j, lm in enumerate(world.landmarks):
            self.colour[i, j] = lm.color
        if self.task == "speaker_listener":
            self.goal[i] = world.landmarks.index(world.agents[0].goal_b)
        self.ended[i] = False
        return self._observe(np.array([i]))[0]

    def reset(self, i: int, seed: int | None = None) -> np.ndarray:
        """Start world i's episode (`TaskEnv.reset`): its joint observation (joint_obs,)."""
        self.envs[i].reset(seed=seed)
        self.t[i] = 0
        return self._load(i)

    def reset_world(self, i: int) -> np.ndarray:
        """A new world inside world i's running episode (`TaskEnv.reset_world`)."""
        if self.t[i] < 0:
            raise RuntimeError("call reset() before reset_world()")
        self.envs[i].reset_world()
        return self._load(i)

    def rng_state(self, i: int) -> dict:
        return self.envs[i].rng_state()

    def set_rng_state(self, i: int, state: dict) -> None:
        self.envs[i].set_rng_state(state)

    # ------------------------------------------------------------------ stepping
    def step(self, actions: np.ndarray) -> VecStep:
        """Apply (E, joint_act) thesis-layout actions to every world and score them."""
        a = np.asarray(actions, dtype=np.float32)
        want = (self.e, self.spec.joint_act_dim)
        if a.shape != want:
            raise ValueError(f"actions have shape {a.shape}, expected {want}")
        if (self.t < 0).any():
            raise RuntimeError("call reset() on every world before step()")
        if (self.t >= self.spec.episode_len).any():
            raise RuntimeError("an episode is over (time limit); call reset()")
        if self.ended.any():
            raise RuntimeError("success ended a world (success_terminal); call reset_world()")
        if not np.isfinite(a).all():
            bad = sorted({int(w) for w in np.nonzero(~np.isfinite(a))[0]})
            raise ValueError(f"non-finite actions in worlds {bad}")
        a = np.minimum(np.maximum(a, self.low), self.high)
        self._physics(a)
        self.t += 1
        every = np.arange(self.e)
        obs = self._observe(every)
        reward, success, collisions = self._score()
        truncated = self.t >= self.spec.episode_len
        terminated = success & self.success_terminal
        self.ended = terminated & ~truncated
        restart = np.zeros(self.e, bool)
        return VecStep(obs, reward, success, collisions, truncated, terminated, restart)

    def _physics(self, a: np.ndarray) -> None:
        """mpe2's World.step on every world: forces, contacts, integration, messages."""
        n = self.n_agents
        force: list[np.ndarray | None] = [None] * (n + self.n_landmarks)
        for j in range(n):
            lo, n_move = self.act_off[j], self.move_dims[j]
            if self.movable[j]:
                # u = zeros + move, times the sensitivity; mpe2 then adds a 0.0 noise
                u = (a[:, lo : lo + n_move].astype(np.float64) + 0.0) * self.accel[j]
                force[j] = u + 0.0
            if self.silent[j]:
                self.comm[:, j] = 0.0
            else:
                self.comm[:, j] = a[:, lo + n_move : self.act_off[j + 1]]
        # Contacts, pair by pair in mpe2's order: an entity's forces arrive from its
        # partners in increasing index order, each added to what it has.
        cs = self.colliders
        for x, ia in enumerate(cs):
            for ib in cs[x + 1 :]:
                delta = self.pos[:, ia] - self.pos[:, ib]
                dist = np.sqrt(delta[:, 0] * delta[:, 0] + delta[:, 1] * delta[:, 1])
                dist_min = self.size[:, ia] + self.size[:, ib]
                k = self.contact_margin
                pen = np.logaddexp(0, -(dist - dist_min) / k) * k
                f = self.contact_force * delta / dist[:, None] * pen[:, None]
                if self.movable[ia]:
                    force[ia] = f + (0.0 if force[ia] is None else force[ia])
                if self.movable[ib]:
                    force[ib] = -f + (0.0 if force[ib] is None else force[ib])
        pos, vel = self.pos, self.vel
        keep = 1 - self.damping
        for j in map(int, np.nonzero(self.movable)[0]):
            f = force[j]
            if self.velocity_first:
                vel[:, j] = vel[:, j] * keep
                if f is not None:
                    vel[:, j] += (f / self.mass[j]) * self.dt
                pos[:, j] += vel[:, j] * self.dt
            else:
                pos[:, j] += vel[:, j] * self.dt
                vel[:, j] = vel[:, j] * keep
                if f is not None:
                    vel[:, j] += (f / self.mass[j]) * self.dt

    def _observe(self, w: np.ndarray) -> np.ndarray:
        """Joint observations (len(w), joint_obs) float32 of worlds w, the spec's layout."""
        out = np.zeros((len(w), self.spec.joint_obs_dim), np.float32)
        pos, vel = self.pos[w], self.vel[w]
        n = self.n_agents
        lms = pos[:, n:]
        for j in range(n):
            lo = self.obs_off[j]
            me = pos[:, j]
            if self.task == "simple":
                parts = [vel[:, j], *(lms[:, k] - me for k in range(self.n_landmarks))]
            elif self.task == "spread":
                parts = [vel[:, j], me]
                parts += [lms[:, k] - me for k in range(self.n_landmarks)]
                parts += [pos[:, o] - me for o in range(n) if o != j]
                parts += [self.comm[w, o] for o in range(n) if o != j]
            elif j == 0:  # the speaker: the goal landmark's colour
                parts = [self.colour[w, self.goal[w]]]
            else:  # the listener: velocity, landmarks, the speaker's message
                parts = [vel[:, j], *(lms[:, k] - me for k in range(self.n_landmarks))]
                parts.append(self.comm[w, 0])
            full = np.concatenate(parts, axis=1)
            keep = self.keep[j]
            out[:, lo : lo + keep] = full[:, :keep]
        return out

    def _dist(self, i: int, j: int) -> np.ndarray:
        d = self.pos[:, i] - self.pos[:, j]
        return np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])

    def _score(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(reward, success, collisions) of every world: `TaskEnv.evaluate`."""
        n, size = self.n_agents, self.size
        collisions = np.zeros(self.e, np.int64)
        ac = self.agent_colliders
        for x, i in enumerate(ac):
            for j in ac[x + 1 :]:
                collisions += self._dist(i, j) < size[:, i] + size[:, j]
        if self.task == "simple":
            success = self._dist(0, n) < size[:, 0] + size[:, n]
            sparse = np.where(success, 0.0, -1.0)
        elif self.task == "speaker_listener":
            goal = n + self.goal
            d = self.pos[np.arange(self.e), goal] - self.pos[:, 1]
            dist = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])
            success = dist < size[:, 1] + size[np.arange(self.e), goal]
            sparse = np.where(success, 0.0, -1.0)
        else:
            uncovered = np.zeros(self.e, np.int64)
            rewarded = np.zeros(self.e, np.int64)
            for k in range(self.n_landmarks):
                lm = n + k
                dists = [self._dist(j, lm) for j in range(n)]
                cov = np.zeros(self.e, bool)
                near = np.zeros(self.e, bool)
                for j, dj in enumerate(dists):
                    cov |= dj < size[:, j] + size[:, lm]
                    near |= dj <= size[:, lm]
                uncovered += ~cov
                rewarded += ~(near if self.landmark_cover else cov)
            sparse = -(rewarded + collisions) / n
            success = uncovered == 0
        reward = sparse.astype(np.float64)
        reward = np.where(self.reward_kinds == "sparse_offset", reward + SPARSE_OFFSET, reward)
        if self.any_dense:
            reward = np.where(self.reward_kinds == "dense", self._dense(), reward)
        return reward, success, collisions

    def _dense(self) -> np.ndarray:
        """mpe2's per-agent rewards averaged (`TaskEnv._dense_reward`)."""
        n, e = self.n_agents, self.e
        glob = np.zeros(e)
        if self.task == "spread":
            for k in range(self.n_landmarks):
                dists = np.stack([self._dist(j, n + k) for j in range(n)], 1)
                glob = glob - dists.min(1)
            per = []
            for j in range(n):
                r = np.zeros(e)
                for o in range(n):
                    if o != j:
                        r = r - 1.0 * (self._dist(o, j) < self.size[:, o] + self.size[:, j])
                per.append(r)
        elif self.task == "simple":
            d = self.pos[:, 0] - self.pos[:, n]
            per = [-(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])]
        else:
            d = self.pos[np.arange(e), n + self.goal] - self.pos[:, 1]
            per = [-(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1])] * n
        if self.local_ratio is not None:
            lr = self.local_ratio
            per = [glob * (1 - lr) + r * lr for r in per]
        # np.mean over each world's agents, as the adapter's np.mean over its list
        return np.mean(np.stack(per, axis=1), axis=1)


class ListTask:
    """Any tasks' envs (a custom PettingZoo task's) behind VecTask's interface, stepped
    one world after another."""

    def __init__(self, envs: Sequence[TaskEnv]) -> None:
        self.envs = list(envs)
        self.e = len(self.envs)
        self.spec = self.envs[0].spec

    def reset(self, i: int, seed: int | None = None) -> np.ndarray:
        return np.concatenate(self.envs[i].reset(seed=seed))

    def reset_world(self, i: int) -> np.ndarray:
        return np.concatenate(self.envs[i].reset_world())

    def rng_state(self, i: int) -> dict:
        return self.envs[i].rng_state()

    def set_rng_state(self, i: int, state: dict) -> None:
        self.envs[i].set_rng_state(state)

    def step(self, actions: np.ndarray) -> VecStep:
        res = [env.step_joint(a) for env, a in zip(self.envs, actions, strict=True)]
        return VecStep(
            np.stack([r.obs for r in res]),
            np.array([r.reward for r in res], np.float64),
            np.array([r.success for r in res]),
            np.array([r.collisions for r in res], np.int64),
            np.array([r.truncated for r in res]),
            np.array([r.terminated for r in res]),
            np.array([r.restart for r in res]),
        )


def vectorize(envs: Sequence[TaskEnv]) -> VecTask | ListTask:
    """E worlds as arrays where the task is built in, else one after another."""
    if isinstance(envs[0], TaskEnv) and not is_custom(envs[0].task):
        return VecTask(envs)
    return ListTask(envs)


def _signature(env: TaskEnv) -> tuple:
    return (
        env.task,
        env.spec,
        env.success_terminal,
        env.landmark_size,
        env._landmark_cover,
        env._velocity_first,
        tuple(env._keep),
    )
