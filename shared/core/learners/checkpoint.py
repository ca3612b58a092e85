"""The batched learner's stacked storage in the reference's per-agent checkpoint format.

A checkpoint is what the reference `MADDPG.state_dict()` writes: per agent, the module
state dicts of its actor, critic and their targets and its two Adam state dicts. The
batched learner reads and writes exactly that, so one checkpoint format serves both
learners (what one writes the other loads) and actors and the evaluator load weights
without knowing how the learner stores them. The only thing the stacked form cannot hold is
per-agent Adam settings or step counts that differ, which the reference's own training
never produces (load_optim refuses them).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import torch

from shared.core.learners.base import AgentDims, LearnerSpec
from shared.core.learners.layers import Stack


class StackedState(Protocol):
    """What the checkpoint functions read and write of a batched learner (its stacks,
    constants, optimizers and counter): named here so that this module does not import
    the learner that imports it."""

    agents: list[AgentDims]
    spec: LearnerSpec
    n: int
    updates: int
    scale: torch.Tensor
    center: torch.Tensor
    actor: Stack
    critic: Stack
    actor_optim: torch.optim.Adam
    critic_optim: torch.optim.Adam


def actor_state(
    learner: StackedState, tensors: Sequence[torch.Tensor], i: int
) -> dict[str, torch.Tensor]:
    """Agent i's actor in shared.core.networks.Actor's state_dict layout (fresh tensors), from
    the learner's actor params or targets."""
    d = learner.agents[i].act_dim
    sd = {"scale": learner.scale[i, 0, :d].clone(), "center": learner.center[i, 0, :d].clone()}
    sd.update(learner.actor.export(tensors, i))
    return sd


def optim_states(optim: torch.optim.Adam, stack: Stack) -> list[dict]:
    """Per-agent Adam state dicts, as the reference's per-agent optimizers write them."""
    n = len(stack.index)
    group = {k: v for k, v in optim.param_groups[0].items() if k != "params"}
    group.update(foreach=None, fused=None, params=list(range(len(stack.params))))
    states = [optim.state.get(p, {}) for p in stack.params]
    # Per-element tensors shaped like the parameter (exp_avg, exp_avg_sq, and
    # max_exp_avg_sq with amsgrad); "step" is one scalar shared by all agents.
    keys = [k for k in states[0] if k != "step"]
    moments = {k: [stack.export([s[k] for s in states], i) for i in range(n)] for k in keys}
    out = []
    for i in range(n):
        state = {}
        if states[0]:
            for j, name in enumerate(stack.export(stack.params, i)):
                state[j] = {"step": states[j]["step"].clone()}
                state[j].update({k: moments[k][i][name] for k in keys})
        out.append({"state": state, "param_groups": [dict(group)]})
    return out


def load_optim(optim: torch.optim.Adam, stack: Stack, sds: Sequence[dict]) -> None:
    """Stack N per-agent Adam states (which must share settings and step count)."""
    skip = ("params", "foreach", "fused", "capturable", "differentiable")
    groups = [{k: v for k, v in sd["param_groups"][0].items() if k not in skip} for sd in sds]
    if any(g != groups[0] for g in groups):
        raise ValueError("the agents' optimizers differ in settings; cannot stack them")
    optim.param_groups[0].update(groups[0])
    optim.state.clear()
    if not any(sd["state"] for sd in sds):
        return
    steps = {float(s["step"]) for sd in sds for s in sd["state"].values()}
    if len(steps) != 1 or not all(len(sd["state"]) == len(stack.params) for sd in sds):
        raise ValueError("the agents' optimizers are at different steps; cannot stack them")
    names = list(stack.export(stack.params, 0))
    step = torch.tensor(steps.pop(), dtype=torch.float32, device=stack.params[0].device)
    for p in stack.params:
        optim.state[p] = {"step": step.clone()}
    for k in (k for k in sds[0]["state"][0] if k != "step"):
        moment = [torch.zeros_like(p) for p in stack.params]
        for i, sd in enumerate(sds):
            stack.load(moment, i, {name: sd["state"][j][k] for j, name in enumerate(names)})
        for p, m in zip(stack.params, moment):
            optim.state[p][k] = m


def export_state(learner: StackedState) -> dict:
    """The learner's state in the reference's format, tensors and primitives only: loads
    with torch.load(weights_only=True) into either MADDPG or BatchedMADDPG."""
    n = range(learner.n)
    actor, critic = learner.actor, learner.critic
    return _on_cpu(
        {
            "algo": learner.spec.algo,
            "updates": learner.updates,
            "actors": [actor_state(learner, actor.params, i) for i in n],
            "critics": [critic.export(critic.params, i) for i in n],
            "actor_targets": [actor_state(learner, actor.targets, i) for i in n],
            "critic_targets": [critic.export(critic.targets, i) for i in n],
            "actor_optims": optim_states(learner.actor_optim, actor),
            "critic_optims": optim_states(learner.critic_optim, critic),
        }
    )


def _on_cpu(tree):
    """Every tensor of a state on the CPU: a checkpoint loads anywhere."""
    if isinstance(tree, torch.Tensor):
        return tree.cpu()
    if isinstance(tree, dict):
        return {k: _on_cpu(v) for k, v in tree.items()}
    if isinstance(tree, list):
        return [_on_cpu(v) for v in tree]
    return tree


def import_state(learner: StackedState, state: dict) -> None:
    """Load a checkpoint written by either learner (same algo and number of agents)."""
    if state["algo"] != learner.spec.algo:
        raise ValueError(f"checkpoint is for {state['algo']}, learner is {learner.spec.algo}")
    for key in ("actors", "critics", "actor_targets", "critic_targets"):
        if len(state[key]) != learner.n:
            raise ValueError(f"checkpoint has {len(state[key])} {key}, learner has {learner.n}")
    learner.updates = int(state["updates"])
    actor, critic = learner.actor, learner.critic
    for key, stack, tensors in (
        ("actors", actor, actor.params),
        ("actor_targets", actor, actor.targets),
        ("critics", critic, critic.params),
        ("critic_targets", critic, critic.targets),
    ):
        for i, sd in enumerate(state[key]):
            stack.load(tensors, i, sd)
    load_optim(learner.actor_optim, actor, state["actor_optims"])
    load_optim(learner.critic_optim, critic, state["critic_optims"])
