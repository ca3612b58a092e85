"""A run's learner and exploration, built from its config.

The one-process trainer and the services (learner, counter) build them here, so they
get the same learner for the same config and, since the seeds derive from the run
seed in one place, the same initial weights and SimHash projections.
"""

from __future__ import annotations

from collections.abc import Callable

from shared.config import TrainConfig
from shared.core.exploration import CountExploration, ExploreSpec
from shared.core.learners import (
    AUTO_MODES,
    MADDPG,
    AgentDims,
    BatchedMADDPG,
    Learner,
    LearnerSpec,
    TunedMADDPG,
)
from shared.envs.tasks import TaskSpec
from shared.run.rollout import derive_seed


def agent_dims(spec: TaskSpec) -> list[AgentDims]:
    """What a learner needs of a task's agents."""
    return [AgentDims(a.obs_dim, a.act_low, a.act_high) for a in spec.agents]


def learner_spec(cfg: TrainConfig) -> LearnerSpec:
    """The run's algorithm settings; its learner seed derives from the run seed."""
    return LearnerSpec(
        algo=cfg.algo,
        hidden=tuple(cfg.hidden),
        lr_actor=cfg.lr_actor,
        lr_critic=cfg.lr_critic,
        gamma=cfg.gamma,
        tau=cfg.tau,
        seed=derive_seed(cfg.seed, "learner"),
        same_init=cfg.same_init,
        flush_denormals=cfg.flush_denormals,
    )


def build_learner(
    cfg: TrainConfig, spec: TaskSpec, contended: Callable[[], bool] | None = None
) -> Learner:
    """`cfg.learner_impl`'s learner; with `learner_lanes: auto` the batched one tuned; the
    batched one's products in `cfg.precision` (the config refuses bf16 for the reference,
    which stays the fp32 definition). On a device other than the CPU the batched one
    runs on one lane, untuned: lanes and torch's thread count are CPU threads.

    `contended()`, polled before each tuned update, says whether other work known to
    the caller runs beside it (ignored by the untuned learners)."""
    agents = agent_dims(spec)
    lspec = learner_spec(cfg)
    if cfg.learner_impl != "batched":
        return MADDPG(agents, lspec)
    if cfg.device != "cpu":  # lanes and the tuner's torch threads are the CPU's
        return BatchedMADDPG(agents, lspec, precision=cfg.precision, device=cfg.device)
    if cfg.learner_lanes == "auto":
        lanes = max(n for n, _ in AUTO_MODES)  # the most lanes a mode runs on
        learner = BatchedMADDPG(
            agents, lspec, lanes=lanes, precision=cfg.precision, device=cfg.device
        )
        return TunedMADDPG(learner, contended)
    return BatchedMADDPG(
        agents, lspec, lanes=cfg.learner_lanes, precision=cfg.precision, device=cfg.device
    )


def build_exploration(cfg: TrainConfig, spec: TaskSpec) -> CountExploration:
    espec = ExploreSpec(
        mode=cfg.explore,
        beta=cfg.beta,
        k=cfg.k,
        hash=cfg.hash,
        key=cfg.key,
        seed=derive_seed(cfg.seed, "simhash"),
        round=cfg.hash_round,
        sketch=None
        if (sk := cfg.count_sketch) is None
        else (sk.columns, sk.depth, sk.conservative),
    )
    return CountExploration(espec, spec.obs_dims, spec.act_dims)


def minibatches_per_update(cfg: TrainConfig) -> int:
    """Minibatches sampled for one update: one shared by all agents, or one per agent
    (`minibatch: per-agent`; with one agent the two are the same)."""
    return cfg.n_agents if cfg.minibatch == "per-agent" else 1
