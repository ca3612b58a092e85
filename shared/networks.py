"""Actor and critic MLPs (appendix A: two hidden layers of 400 and 300, ReLU)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn


def mlp(in_dim: int, out_dim: int, hidden: Sequence[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    last = in_dim
    for h in hidden:
        layers += [nn.Linear(last, h), nn.ReLU()]
        last = h
    layers.append(nn.Linear(last, out_dim))
    return nn.Sequential(*layers)


class Actor(nn.Module):
    """mu_i(o_i): a tanh output rescaled into the agent's action box [low, high]."""

    def __init__(
        self, obs_dim: int, low: Sequence[float], high: Sequence[float], hidden: Sequence[int]
    ) -> None:
        super().__init__()
        self.net = mlp(obs_dim, len(low), hidden)
        low_t = torch.as_tensor(low, dtype=torch.float32)
        high_t = torch.as_tensor(high, dtype=torch.float32)
        self.register_buffer("scale", (high_t - low_t) / 2)
        self.register_buffer("center", (high_t + low_t) / 2)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.center + self.scale * torch.tanh(self.net(obs))


class Critic(nn.Module):
    """Q_i(inputs, actions) -> (B,). Inputs are o_i (Dis) or s (Cen); actions a_i or x."""

    def __init__(self, in_dim: int, hidden: Sequence[int]) -> None:
        super().__init__()
        self.net = mlp(in_dim, 1, hidden)

    def forward(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([obs, act], dim=-1)).squeeze(-1)


class JointPolicy:
    """The actors alone (what actor and evaluator processes run), for joint observations."""

    def __init__(
        self,
        obs_dims: Sequence[int],
        lows: Sequence[Sequence[float]],
        highs: Sequence[Sequence[float]],
        hidden: Sequence[int],
    ) -> None:
        self.actors = [Actor(o, lo, hi, hidden) for o, lo, hi in zip(obs_dims, lows, highs)]
        self.bounds = [0, *torch.cumsum(torch.tensor(list(obs_dims)), 0).tolist()]

    @torch.no_grad()
    def __call__(self, obs):
        o = torch.as_tensor(obs, dtype=torch.float32)
        b = self.bounds
        return torch.cat(
            [actor(o[..., b[i] : b[i + 1]]) for i, actor in enumerate(self.actors)], dim=-1
        ).numpy()

    def load(self, weights: Sequence[dict]) -> None:
        load_actor_weights(self.actors, weights)


def actor_weights(actors: Sequence[nn.Module]) -> list[dict]:
    """Actor parameters and buffers as numpy arrays (for the wire)."""
    return [{k: v.detach().cpu().numpy() for k, v in m.state_dict().items()} for m in actors]


def load_actor_weights(actors: Sequence[nn.Module], weights: Sequence[dict]) -> None:
    if len(weights) != len(actors):
        raise ValueError(f"weights for {len(weights)} agents, policy has {len(actors)}")
    for m, sd in zip(actors, weights):
        m.load_state_dict({k: torch.as_tensor(v) for k, v in sd.items()})
