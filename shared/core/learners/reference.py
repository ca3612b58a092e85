"""DDPG, Distributed MADDPG and Centralized MADDPG: the reference per-agent update.

Each agent i has an actor mu_i(o_i) and a critic Q_i. Dis-MADDPG (and DDPG, its
one-agent case) trains Q_i(o_i, a_i); Cen-MADDPG trains Q_i(s, x) on all
observations and actions, and the actor gradient flows only through agent i's own
action, the other actions coming from the batch (thesis eq. 14-15).

By default all agents learn from one shared minibatch per update (as the original
MADDPG code does), so one bonus query serves the whole update; `minibatch: per-agent`
gives each agent its own (the thesis code). Within an update, agents are independent:
agent i's critic and actor steps touch only agent i's parameters and targets are read
before any soft update, so the order of agents does not matter.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from shared.core.joint import offsets
from shared.core.learners.base import (
    AgentDims,
    LearnerSpec,
    agent_slice,
    check_agents,
    denormals_flushed,
)
from shared.core.networks import Actor, Critic


class MADDPG:
    """The networks, optimizers and one update step; no environment, no I/O."""

    def __init__(self, agents: Sequence[AgentDims], spec: LearnerSpec) -> None:
        check_agents(agents, spec)
        self.agents = list(agents)
        self.spec = spec
        self.n = len(agents)
        self.centralized = spec.algo == "cen-maddpg"
        self.obs_off = offsets([a.obs_dim for a in agents])
        self.act_off = offsets([a.act_dim for a in agents])
        joint_in = self.obs_off[-1] + self.act_off[-1]

        def critic(a: AgentDims) -> Critic:
            return Critic(joint_in if self.centralized else a.obs_dim + a.act_dim, spec.hidden)

        with torch.random.fork_rng(devices=[]):  # seeded weights; the caller's RNG untouched
            torch.manual_seed(spec.seed)
            if spec.same_init:  # reseeded per agent: equal shapes, equal weights
                self.actors, self.critics = [], []
                for a in agents:
                    torch.manual_seed(spec.seed)
                    self.actors.append(Actor(a.obs_dim, a.act_low, a.act_high, spec.hidden))
                    self.critics.append(critic(a))
            else:
                self.actors = [Actor(a.obs_dim, a.act_low, a.act_high, spec.hidden) for a in agents]
                self.critics = [critic(a) for a in agents]
        self.actor_targets = [copy.deepcopy(m).requires_grad_(False) for m in self.actors]
        self.critic_targets = [copy.deepcopy(m).requires_grad_(False) for m in self.critics]
        self.actor_optims = [
            torch.optim.Adam(m.parameters(), lr=spec.lr_actor) for m in self.actors
        ]
        self.critic_optims = [
            torch.optim.Adam(m.parameters(), lr=spec.lr_critic) for m in self.critics
        ]
        self.updates = 0

    # ------------------------------------------------------------------ acting
    def obs_slice(self, joint: torch.Tensor, i: int) -> torch.Tensor:
        return agent_slice(joint, self.obs_off, i)

    def act_slice(self, joint: torch.Tensor, i: int) -> torch.Tensor:
        return agent_slice(joint, self.act_off, i)

    @torch.no_grad()
    def act(self, obs: np.ndarray) -> np.ndarray:
        """Deterministic joint actions for joint observations (B, joint_obs) -> (B, joint_act)."""
        o = torch.as_tensor(obs, dtype=torch.float32)
        return torch.cat(
            [actor(self.obs_slice(o, i)) for i, actor in enumerate(self.actors)], dim=-1
        ).numpy()

    # ----------------------------------------------------------------- learning
    def _critic_input(self, i: int, obs: torch.Tensor, act: torch.Tensor):
        if self.centralized:
            return obs, act
        return self.obs_slice(obs, i), self.act_slice(act, i)

    def tensors(self, *arrays: np.ndarray) -> list[torch.Tensor]:
        return [torch.as_tensor(a, dtype=torch.float32) for a in arrays]

    @torch.no_grad()
    def target_actions(self, next_obs: torch.Tensor) -> torch.Tensor:
        """mubar_1(o'_1), ..., mubar_N(o'_N), joined: computed once per update."""
        return torch.cat(
            [mu(self.obs_slice(next_obs, j)) for j, mu in enumerate(self.actor_targets)], -1
        )

    @torch.no_grad()
    def target_q(
        self,
        i: int,
        rew: torch.Tensor,
        next_obs: torch.Tensor,
        done: torch.Tensor,
        next_act: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """y = r'_i + gamma (1 - done) Qbar_i(s', mubar_1(o'_1), ..., mubar_N(o'_N))."""
        if next_act is None:
            next_act = self.target_actions(next_obs)
        qf_next_target = self.critic_targets[i](*self._critic_input(i, next_obs, next_act))
        return rew[:, i] + self.spec.gamma * (1.0 - done) * qf_next_target

    def critic_step(
        self, i: int, obs: torch.Tensor, act: torch.Tensor, next_q_value: torch.Tensor
    ) -> float:
        qf_a_values = self.critics[i](*self._critic_input(i, obs, act))
        qf_loss = F.mse_loss(qf_a_values, next_q_value)
        self.critic_optims[i].zero_grad(set_to_none=True)
        qf_loss.backward()
        self.critic_optims[i].step()
        return qf_loss.item()

    def actor_step(self, i: int, obs: torch.Tensor, act: torch.Tensor) -> float:
        """Maximise Q_i with a_i = mu_i(o_i); the other agents' actions come from the batch."""
        a_i = self.actors[i](self.obs_slice(obs, i))
        if self.centralized:
            parts = [a_i if j == i else self.act_slice(act, j) for j in range(self.n)]
            q_in = (obs, torch.cat(parts, -1))
        else:
            q_in = (self.obs_slice(obs, i), a_i)
        critic = self.critics[i].requires_grad_(False)  # no gradient for critic weights
        try:
            actor_loss = -critic(*q_in).mean()
            self.actor_optims[i].zero_grad(set_to_none=True)
            actor_loss.backward()
            self.actor_optims[i].step()
        finally:
            critic.requires_grad_(True)
        return actor_loss.item()

    def update(
        self,
        obs: np.ndarray,
        act: np.ndarray,
        rew: np.ndarray,
        next_obs: np.ndarray,
        done: np.ndarray,
    ) -> dict[str, float]:
        """One critic and one actor step per agent, then soft target updates.

        rew is (B, N): the extrinsic reward plus agent i's bonus in column i. With a
        leading agent axis on every array (one minibatch per agent, see `Learner`),
        agent i's steps use batch i alone.
        """
        obs_t, act_t, rew_t, next_t, done_t = self.tensors(obs, act, rew, next_obs, done)
        with denormals_flushed(self.spec.flush_denormals):
            critic_losses, actor_losses = [], []
            per_agent = obs_t.dim() == 3
            # Targets do not move until soft_update: target actions once per minibatch.
            next_acts = (
                [self.target_actions(n) for n in next_t]
                if per_agent
                else [self.target_actions(next_t)]
            )
            batch = (obs_t, act_t, rew_t, next_t, done_t)
            for i in range(self.n):
                o, a, r, o2, d = (t[i] for t in batch) if per_agent else batch
                y = self.target_q(i, r, o2, d, next_acts[i if per_agent else 0])
                critic_losses.append(self.critic_step(i, o, a, y))
                actor_losses.append(self.actor_step(i, o, a))
            self.soft_update()
        self.updates += 1
        return {
            "critic_loss": float(np.mean(critic_losses)),
            "actor_loss": float(np.mean(actor_losses)),
        }

    @torch.no_grad()
    def soft_update(self) -> None:
        """theta' <- tau theta + (1 - tau) theta' for every target network."""
        tau = self.spec.tau
        for nets, targets in (
            (self.actors, self.actor_targets),
            (self.critics, self.critic_targets),
        ):
            for net, target in zip(nets, targets):
                tp: list[torch.Tensor] = list(target.parameters())
                src: list[torch.Tensor] = list(net.parameters())
                torch._foreach_lerp_(tp, src, tau)

    # ----------------------------------------------------------------- state
    def state_dict(self) -> dict:
        """Tensors and primitives only, so it loads with torch.load(weights_only=True)."""
        return {
            "algo": self.spec.algo,
            "updates": self.updates,
            "actors": [m.state_dict() for m in self.actors],
            "critics": [m.state_dict() for m in self.critics],
            "actor_targets": [m.state_dict() for m in self.actor_targets],
            "critic_targets": [m.state_dict() for m in self.critic_targets],
            "actor_optims": [o.state_dict() for o in self.actor_optims],
            "critic_optims": [o.state_dict() for o in self.critic_optims],
        }

    def load_state_dict(self, state: dict) -> None:
        if state["algo"] != self.spec.algo:
            raise ValueError(f"checkpoint is for {state['algo']}, learner is {self.spec.algo}")
        if len(state["actors"]) != self.n:
            raise ValueError(f"checkpoint has {len(state['actors'])} agents, learner has {self.n}")
        self.updates = int(state["updates"])
        for key in ("actors", "critics", "actor_targets", "critic_targets"):
            for m, sd in zip(getattr(self, key), state[key]):
                m.load_state_dict(sd)
        for key in ("actor_optims", "critic_optims"):
            for o, sd in zip(getattr(self, key), state[key]):
                o.load_state_dict(sd)

    def actor_weights(self) -> list[dict[str, torch.Tensor]]:
        return [m.state_dict() for m in self.actors]

    def load_actor_weights(self, weights: Sequence[dict[str, Any]]) -> None:
        for m, sd in zip(self.actors, weights):
            m.load_state_dict(sd)

    def stats(self) -> dict[str, float]:
        """Nothing to report: one plain PyTorch update per agent, on the process's threads."""
        return {}
