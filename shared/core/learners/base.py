"""What a learner is to the code that drives it, and what every learner is built from.

The one-process trainer and the cluster's learner service hold a learner only through
`Learner`, so the reference (`MADDPG`), the batched learner (`BatchedMADDPG`) and the
thread-tuning wrapper (`TunedMADDPG`) are interchangeable there and are chosen by the
config alone (shared/run/factories.py). Everything else a learner has (networks, stacks,
per-agent steps) is for tests and benchmarks, which know which one they built.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import torch

from shared.core.learners.fused import kernel

if TYPE_CHECKING:  # annotations only
    import numpy as np

ALGOS = ("ddpg", "dis-maddpg", "cen-maddpg")


@dataclass(frozen=True)
class AgentDims:
    """One agent's observation size and action box, all a learner needs of a task."""

    obs_dim: int
    act_low: tuple[float, ...]
    act_high: tuple[float, ...]

    @property
    def act_dim(self) -> int:
        return len(self.act_low)


@dataclass(frozen=True)
class LearnerSpec:
    """The algorithm and its settings; `seed` fixes the initial weights."""

    algo: str = "cen-maddpg"
    hidden: tuple[int, ...] = (400, 300)
    lr_actor: float = 1e-3
    lr_critic: float = 1e-3
    gamma: float = 0.99
    tau: float = 0.005
    seed: int = 0
    # Agents of the same shape start from identical weights: torch reseeded with `seed`
    # before each agent's actor and critic (what the thesis code's per-agent setup did).
    same_init: bool = False
    # Subnormal floats are flushed to zero inside an update (`denormals_flushed`).
    flush_denormals: bool = True


@contextmanager
def denormals_flushed(on: bool) -> Iterator[None]:
    """Within: subnormal floats (below 1.2e-38) read and made as zero (x86 DAZ and FTZ),
    in this thread and in torch's OpenMP threads (through fused.py's library where it
    builds; without a C compiler only in the threads torch starts meanwhile, which take
    their creator's mode: torch starts its pool at its first two-thread op, in a learner
    an update's).

    Why: Adam's first moment of a weight whose gradient stays 0 (a dead ReLU unit) decays
    by beta1 per step into the subnormal range and stays there (0.9 x the smallest
    subnormal rounds back to it), and on some CPUs every multiply on a subnormal costs a
    microcode assist, in every Adam step of those weights (docs/performance.md,
    "Subnormal Adam moments", has how many and what it costs). What it changes: values
    below 1.2e-38 become 0 (docs/fidelity.md L9)."""
    if not on or getattr(_flushing, "on", False):  # off, or an outer one holds it
        yield
        return
    # torch's pool of OpenMP threads keeps the mode its threads started with: set theirs
    # too, through the fused kernel's library, which shares torch's OpenMP runtime.
    threads = torch.get_num_threads()
    pool = kernel() if threads > 1 else None
    torch.set_flush_denormal(True)
    if pool is not None:
        pool.flush_denormals(True, threads)
    _flushing.on = True
    try:
        yield
    finally:
        _flushing.on = False
        if pool is not None:
            pool.flush_denormals(False, threads)
        torch.set_flush_denormal(False)


_flushing = threading.local()  # whether this thread is inside denormals_flushed


class Losses(Mapping[str, float]):
    """An update's mean `critic_loss` and `actor_loss`, read from the learner's device
    only when a caller reads one (as floats, both at once, then kept).

    Why: reading them at the end of every update is a host read that waits for the
    device to finish the update, and no caller uses them at every update; kept as a
    tensor, the next update is queued behind this one without a wait. On the CPU the
    values read are those an eager read gives."""

    KEYS = ("critic_loss", "actor_loss")

    def __init__(self, values: torch.Tensor) -> None:
        self.tensor = values  # (2,): the losses in KEYS' order, where the update ran
        self._read: dict[str, float] | None = None

    def __getitem__(self, key: str) -> float:
        if self._read is None:
            self._read = dict(zip(self.KEYS, self.tensor.tolist()))
        return self._read[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.KEYS)

    def __len__(self) -> int:
        return len(self.KEYS)

    def __repr__(self) -> str:
        return f"Losses({dict(self) if self._read is not None else 'unread'})"


def check_agents(agents: Sequence[AgentDims], spec: LearnerSpec) -> None:
    """Refuse an unknown algorithm, and DDPG with other than one agent (every learner
    refuses the same, so a config fails the same way whichever one it picks)."""
    if spec.algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {spec.algo!r}")
    if spec.algo == "ddpg" and len(agents) != 1:
        raise ValueError("ddpg trains one agent; use dis-maddpg or cen-maddpg")


def agent_slice(joint: torch.Tensor, offsets: Sequence[int], i: int) -> torch.Tensor:
    """Agent i's block of joint vectors (..., joint) laid out by `shared.core.joint.offsets`."""
    return joint[..., offsets[i] : offsets[i + 1]]


@runtime_checkable
class Learner(Protocol):
    """Networks, optimizers and the update step of DDPG / Dis- / Cen-MADDPG; no
    environment, no I/O. Joint batches are laid out as the replay buffer stores them:
    agents in task order, observations (B, sum obs_dims), actions (B, sum act_dims).

    `update` takes one minibatch for all agents (obs (B, joint), rew (B, N) with agent
    i's reward in column i, done (B,)), or one minibatch per agent with a leading agent
    axis (obs (N, B, joint), rew (N, B, N), done (N, B)): agent i then learns from
    batch i alone (`minibatch: per-agent`, the thesis code)."""

    @property
    def updates(self) -> int:
        """Updates done so far (restored with the state)."""
        ...

    def update(
        self,
        obs: np.ndarray,
        act: np.ndarray,
        rew: np.ndarray,
        next_obs: np.ndarray,
        done: np.ndarray,
    ) -> Mapping[str, float]:
        """One critic and one actor step for every agent, then soft target updates.
        rew is (B, N): the extrinsic reward plus agent i's bonus in column i. Returns
        the mean `critic_loss` and `actor_loss` over agents (the batched learner's read
        from its device only when read: `Losses`)."""
        ...

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Deterministic joint actions for joint observations (..., joint_obs)."""
        ...

    def actor_weights(self) -> list[dict[str, torch.Tensor]]:
        """Per agent, a state dict for shared.core.networks.Actor (what actors and the
        evaluator load)."""
        ...

    def load_actor_weights(self, weights: Sequence[dict[str, Any]]) -> None: ...

    def state_dict(self) -> dict:
        """The reference's per-agent checkpoint format, tensors and primitives only:
        loads with torch.load(weights_only=True) into any learner of the same shape."""
        ...

    def load_state_dict(self, state: dict) -> None: ...

    def stats(self) -> dict[str, float]:
        """How the update runs (lanes, threads and the tuner's picks), for the metrics;
        empty for the reference."""
        ...
