"""Actor and critic MLPs (appendix A: two hidden layers of 400 and 300, ReLU)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from shared.core.joint import offsets


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

    scale: torch.Tensor  # buffers (registered in __init__, saved in the state dict)
    center: torch.Tensor

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
    """The actors alone (what actor and evaluator processes run), for joint observations.

    It computes in numpy from copies of the actors' weights, refreshed by `load`: at the
    batch sizes of acting (1 for an actor, 10 for the evaluator's lockstep episodes) a
    torch module call is mostly per-op overhead, and numpy's forward takes less time,
    which the other services' spare CPU is worth on 2 cores (docs/performance.md,
    "Evaluation and collection"). The modules stay for loading weights
    (`load_state_dict` checks names and shapes); outputs equal theirs up to float32
    rounding (tests/test_networks.py).
    """

    def __init__(
        self,
        obs_dims: Sequence[int],
        lows: Sequence[Sequence[float]],
        highs: Sequence[Sequence[float]],
        hidden: Sequence[int],
    ) -> None:
        self.actors = [Actor(o, lo, hi, hidden) for o, lo, hi in zip(obs_dims, lows, highs)]
        self.layout = actor_layout(self.actors)  # what `load` takes (`weights_error`)
        self.bounds = offsets(obs_dims)
        self._refresh()

    @classmethod
    def for_task(cls, spec: Any, hidden: Sequence[int]) -> JointPolicy:
        """The policy for a task's agents (`shared.envs.tasks.TaskSpec`: its obs_dims and each
        agent's action box), as actor and evaluator processes build it."""
        agents = spec.agents
        return cls(spec.obs_dims, [a.act_low for a in agents], [a.act_high for a in agents], hidden)

    def _refresh(self) -> None:
        """Copy each actor's layers as (W^T, b) and its box as (center, scale) for numpy.

        One attribute is replaced as a whole, so a call never mixes two loads."""

        def arr(t: torch.Tensor) -> np.ndarray:
            return t.detach().cpu().numpy()

        self._net = [
            (
                [
                    (arr(m.weight).T.copy(), arr(m.bias).copy())
                    for m in a.net
                    if isinstance(m, nn.Linear)
                ],
                (arr(a.center).copy(), arr(a.scale).copy()),
            )
            for a in self.actors
        ]

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Joint observations (..., joint_obs) -> joint actions (..., joint_act), float32."""
        o = np.asarray(obs, dtype=np.float32)
        b = self.bounds
        out = []
        for i, (layers, (center, scale)) in enumerate(self._net):
            x = o[..., b[i] : b[i + 1]]
            for k, (w_t, bias) in enumerate(layers):
                x = x @ w_t
                x += bias
                if k < len(layers) - 1:
                    np.maximum(x, 0.0, out=x)
            np.tanh(x, out=x)
            x *= scale
            x += center
            out.append(x)
        return np.concatenate(out, axis=-1)

    def load(self, weights: Sequence[dict]) -> None:
        load_actor_weights(self.actors, weights)
        self._refresh()


# Per agent, its actor's parameter and buffer names with their shapes.
Layout = list[dict[str, tuple[int, ...]]]


def actor_layout(actors: Sequence[nn.Module]) -> Layout:
    """Per agent, the names and shapes of its actor's state dict: the weights a
    `Weights` message must carry for these actors (`weights_error`)."""
    return [{k: tuple(v.shape) for k, v in m.state_dict().items()} for m in actors]


def weights_error(weights: Any, layout: Layout) -> str | None:
    """Why `weights` (a `Weights` message's `actors`) are not weights for actors of
    `layout`, or None: one state dict per agent with exactly its actor's names, each a
    finite float32 array of its shape. Loading anything else raised in the actor's or
    evaluator's loop (ending the process), or loaded only part of it (the stacked
    learners read the names they know; a zip over the agents ignores extra ones)."""
    if not isinstance(weights, list) or len(weights) != len(layout):
        count = len(weights) if isinstance(weights, list) else "no list of"
        return f"weights for {count} agents, the policy has {len(layout)}"
    for i, (sd, shapes) in enumerate(zip(weights, layout)):
        if not isinstance(sd, dict) or set(sd) != set(shapes):
            names = sorted(map(str, sd)) if isinstance(sd, dict) else type(sd).__name__
            return f"agent {i}: parameters {names!s:.200}, the policy's {sorted(shapes)}"
        for name, shape in shapes.items():
            arr = sd[name]
            if not isinstance(arr, np.ndarray) or arr.dtype != np.float32 or arr.shape != shape:
                what = f"{arr.dtype} {arr.shape}" if isinstance(arr, np.ndarray) else "no array"
                return f"agent {i}: {name} is {what}, the policy's float32 {shape}"
            if not np.isfinite(arr).all():
                return f"agent {i}: {name} has non-finite values"
    return None


def actor_weights(actors: Sequence[nn.Module]) -> list[dict]:
    """Actor parameters and buffers as numpy arrays (for the wire)."""
    return weights_as_arrays([m.state_dict() for m in actors])


def weights_as_arrays(weights: Sequence[dict]) -> list[dict]:
    """State dicts of tensors (e.g. a learner's `actor_weights()`) as numpy arrays, for
    the wire."""
    return [{k: v.detach().cpu().numpy() for k, v in sd.items()} for sd in weights]


def load_actor_weights(actors: Sequence[nn.Module], weights: Sequence[dict]) -> None:
    if len(weights) != len(actors):
        raise ValueError(f"weights for {len(weights)} agents, policy has {len(actors)}")
    for m, sd in zip(actors, weights):
        m.load_state_dict({k: torch.as_tensor(v) for k, v in sd.items()})
