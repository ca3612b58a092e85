"""R runs of one task and network shape in one learner: a figure's seeds and arms
updated by one call.

`GroupMADDPG` is the batched update (`StackedMADDPG`, batched.py) with a run axis: its
stacks hold R x N networks (run r's agent i at entry r * N + i), so one layer of every
agent of every run is one `baddbmm`, one Adam pass steps every run's weights, one `lerp`
soft-updates every target. Each run keeps its own initial weights (its own `LearnerSpec`
seed), its own Adam moments (elementwise, so stacking them changes nothing), and reads
only its own batch: run r's critics read run r's joint rows, never another run's. The
products are per stack entry and independent of how many entries there are, so run r's
update is the one `BatchedMADDPG` alone does on the same batch
(tests/test_group_learner.py, bit for bit in fp32 and in bf16).

Inputs carry the run axis first: obs (R, B, joint) with one minibatch per run shared
by its agents, or (R, N, B, joint) with one per agent (`minibatch: per-agent`); rew
(R, B, N) or (R, N, B, N); done (R, B) or (R, N, B). What the runs of a group must
share is their update's arithmetic: algorithm, hidden sizes, learning rates, gamma,
tau and the subnormal flushing (`group_key`); seeds and `same_init` may differ.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from shared.core.learners.base import AgentDims, LearnerSpec
from shared.core.learners.batched import BatchedMADDPG, StackedMADDPG, UpdateInput, host_array
from shared.core.learners.layers import Stack, mlp_forward

#: LearnerSpec fields every run of a group must share.
#: Elements of a whole number of vectors for every elementwise kernel (fp32 and bf16).
VECTOR_SPAN = 64

SHARED_FIELDS = ("algo", "hidden", "lr_actor", "lr_critic", "gamma", "tau", "flush_denormals")


class GroupMADDPG(StackedMADDPG):
    """R runs' learners as one (see the module docstring); lanes are not used. A run's
    own learner, state and actors are `BatchedMADDPG`'s (`run_learner`, `run_state_dict`,
    `run_actor_weights`): the group holds no state of its own to save."""

    def __init__(
        self,
        agents: Sequence[AgentDims],
        specs: Sequence[LearnerSpec],
        precision: str = "fp32",
        fused: bool | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        specs = list(specs)
        if not specs:
            raise ValueError("a group needs at least one run")
        for field in SHARED_FIELDS:
            values = {getattr(s, field) for s in specs}
            if len(values) > 1:
                raise ValueError(f"the runs of a group must share {field}; got {sorted(values)}")
        self.specs = specs
        self.runs = r = len(specs)
        self._per_entry = False
        # Built on the CPU, R runs' stacks (`_stack_runs`), then moved to the device once.
        super().__init__(agents, specs[0], lanes=1, precision=precision, fused=fused, device=device)
        n = self.n
        # Per-agent constants, tiled per run.
        tile = lambda t: t.repeat(r, *([1] * (t.dim() - 1)))  # noqa: E731
        self.scale, self.center = tile(self.scale), tile(self.center)
        if self.centralized:
            self._keep, self._place_idx = tile(self._keep), tile(self._place_idx)
            self._own_cols = tile(self._own_cols)
        self._tiled = {id(i): tile(i) for i in (self._obs_idx, self._act_idx)}
        self._agent_of = torch.arange(n, device=self.device).repeat(r)  # entry -> its agent

    def _stack_runs(self) -> None:
        """One run's stacks (the first spec's, just built on the CPU) widened to R copies
        of their layout, each run's from its own seed, before they move to the device."""
        r, n = self.runs, self.n
        one = (self.actor, self.critic)
        self.actor, self.critic = (self._widen(s, r) for s in one)
        for run, spec in enumerate(self.specs):
            other = None if run == 0 else BatchedMADDPG(self.agents, spec)  # on the CPU
            init = one if other is None else (other.actor, other.critic)
            for wide, single in zip((self.actor, self.critic), init):
                for dst, src in ((wide.params, single.params), (wide.targets, single.targets)):
                    for d, s in zip(dst, src):
                        d[run * n : (run + 1) * n] = s

    def _parts(self, tensors: Sequence[torch.Tensor]) -> list[torch.Tensor]:
        """Each stacked tensor whole, or as R views run by run: the elementwise kernels
        (Adam, the soft update) take vectors of a tensor from its start and its last
        elements one by one, with other rounding (fused multiply-adds). Where a run's
        part is a whole number of vectors (of 64 elements, any kernel's width or more)
        its elements fall on vectors as they do in its tensor alone; any other tensor is
        given run by run, so that they fall where they fall alone. That is the CPU's
        rule (its rows equal a run's alone, bit for bit); on an accelerator every tensor
        goes whole, one kernel for all runs."""
        if self.device.type != "cpu":
            return list(tensors)
        n, runs = self.n, self.runs
        # On several threads torch splits a large tensor at its own boundaries: per run.
        whole_ok = torch.get_num_threads() == 1
        out: list[torch.Tensor] = []
        for t in tensors:
            if whole_ok and (t.numel() // runs) % VECTOR_SPAN == 0:
                out.append(t)
            else:
                out += [t[r * n : (r + 1) * n] for r in range(runs)]
        return out

    def _part_counts(self, tensors: Sequence[torch.Tensor]) -> list[int]:
        """How many parts `_parts` gives each tensor."""
        if self.device.type != "cpu":
            return [1] * len(tensors)
        whole_ok = torch.get_num_threads() == 1
        return [
            1 if whole_ok and (t.numel() // self.runs) % VECTOR_SPAN == 0 else self.runs
            for t in tensors
        ]

    @staticmethod
    def _widen(stack: Stack, runs: int) -> Stack:
        """A stack of `runs` copies of `stack`'s networks (zeros), same layout per copy."""
        layers = len(stack.index[0])
        sizes = [stack.params[0].shape[2]] + [stack.params[2 * k].shape[1] for k in range(layers)]
        n = len(stack.index)
        ins = [stack.index[i][0][0] for i in range(n)] * runs
        outs = [stack.index[i][-1][1] for i in range(n)] * runs
        return Stack(n * runs, sizes, ins, outs)

    # ------------------------------------------------------------- layout
    def _per_agent(self, joint: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """Each entry's agent block, zero-padded, (R*N, rows, pad): in an update on one
        minibatch per entry, of (R*N, rows, joint), else of (R, rows, joint) per run."""
        if self._per_entry:
            return self._split_entries(joint, idx)
        return self._split_runs(joint, idx)

    def _split_runs(self, joint: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """(R, rows, joint) -> (R*N, rows, pad): run r's rows for each of its agents."""
        padded = torch.nn.functional.pad(joint, (0, 1))
        rows = joint.shape[1]
        split = padded[:, :, idx]  # (R, rows, N, pad)
        return split.permute(0, 2, 1, 3).reshape(self.runs * self.n, rows, idx.shape[1])

    def _split_entries(self, joint: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """(R*N, rows, joint) -> (R*N, rows, pad): entry e's agent block of its own rows."""
        padded = torch.nn.functional.pad(joint, (0, 1))
        rows = joint.shape[1]
        tiled = self._tiled[id(idx)]
        return torch.gather(padded, 2, tiled[:, None, :].expand(-1, rows, -1))

    def _joint_act(self, per_agent: torch.Tensor) -> torch.Tensor:
        """(R*N, rows, act_pad) -> (R, rows, joint_act): each run's joint actions."""
        r, n = self.runs, self.n
        rows = per_agent.shape[1]
        x = per_agent.reshape(r, n, rows, self.act_pad).permute(0, 2, 1, 3)
        return x.reshape(r, rows, n * self.act_pad)[..., self._joint_act_idx]

    def _entries(self, x: torch.Tensor) -> torch.Tensor:
        """(R, rows, D) per run -> (R*N, rows, D): what each of a run's networks reads."""
        r, rows = x.shape[:2]
        return x.unsqueeze(1).expand(r, self.n, rows, x.shape[2]).reshape(r * self.n, rows, -1)

    def _critic_input(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        if not self.centralized:
            return super()._critic_input(obs, act)
        joint = torch.cat([obs, act], -1)
        return joint if self._per_entry else self._entries(joint)

    # ------------------------------------------------------------- acting
    def act(self, obs: np.ndarray) -> np.ndarray:
        """Deterministic joint actions of every run: (R, ..., joint_obs) -> (R, ..., joint_act)."""
        return host_array(self.act_on_device(obs))

    def act_on_device(self, obs: np.ndarray) -> torch.Tensor:
        """`act`'s actions as a tensor on the learner's device, not read from it."""
        if len(obs) != self.runs:
            raise ValueError(f"obs has {len(obs)} runs, the group {self.runs}")
        (o,) = self.tensors(obs)
        lead = o.shape[1:-1]
        o_pad = self._split_runs(o.reshape(self.runs, -1, self.joint_obs), self._obs_idx)
        mu = self._squash(torch.tanh(mlp_forward(self.actor.params, o_pad)[-1]))
        return self._joint_act(mu).reshape(self.runs, *lead, self.joint_act)

    # ------------------------------------------------------------- learning
    def _target_q(
        self,
        weights: tuple[list[torch.Tensor], list[torch.Tensor]],
        rew: torch.Tensor,
        next_obs: torch.Tensor,
        done: torch.Tensor,
    ) -> torch.Tensor:
        actor, critic = weights
        r, n = self.runs, self.n
        gamma = self.spec.gamma
        if self._per_entry:  # (R*N, B, joint): entry e's own minibatch
            rows = next_obs.shape[1]
            if self.centralized:
                # run r's actors on all of run r's N minibatches (N x B rows)
                runs_rows = next_obs.reshape(r, n * rows, -1)
                every = self._mu(actor, self._split_runs(runs_rows, self._obs_idx))
                joint = self._joint_act(every).reshape(r * n, rows, -1)
                q_in = torch.cat([next_obs, joint], -1)
            else:
                own = self._per_agent(next_obs, self._obs_idx)
                q_in = torch.cat([own, self._mu(actor, own)], -1)
            q = self._q(critic, q_in)
            entries = torch.arange(r * n, device=self.device)
            return rew[entries, :, self._agent_of] + gamma * (1.0 - done) * q
        next_obs_pad = self._per_agent(next_obs, self._obs_idx)
        next_act = self._mu(actor, next_obs_pad)
        if self.centralized:
            q_in = self._entries(torch.cat([next_obs, self._joint_act(next_act)], -1))
        else:
            q_in = torch.cat([next_obs_pad, next_act], -1)
        q = self._q(critic, q_in)
        rows = next_obs.shape[1]
        y_rew = rew.permute(0, 2, 1).reshape(r * n, rows)
        not_done = (1.0 - done.reshape(r, 1, rows)).expand(r, n, rows).reshape(r * n, rows)
        return y_rew + gamma * not_done * q

    def update(
        self,
        obs: UpdateInput,
        act: UpdateInput,
        rew: UpdateInput,
        next_obs: UpdateInput,
        done: UpdateInput,
    ) -> Mapping[str, float]:
        """One critic and one actor step for every agent of every run, then the soft
        updates: run r's from its own batch (shapes in the module docstring). The
        arrays may be tensors on the learner's device already (a graph-captured update)."""
        obs, act, rew, next_obs, done = (
            x if isinstance(x, torch.Tensor) else np.asarray(x)
            for x in (obs, act, rew, next_obs, done)
        )
        if obs.shape[0] != self.runs:
            raise ValueError(f"obs has {obs.shape[0]} runs, the group {self.runs}")
        self._per_entry = obs.ndim == 4
        if self._per_entry:  # (R, N, B, ...) -> (R*N, B, ...)
            flat = lambda x: x.reshape(self.runs * self.n, *x.shape[2:])  # noqa: E731
            obs, act, rew, next_obs, done = map(flat, (obs, act, rew, next_obs, done))
        try:
            return self.update_on(1, obs, act, rew, next_obs, done)
        finally:
            self._per_entry = False

    # ------------------------------------------------------------- per run
    def run_learner(self, run: int) -> BatchedMADDPG:
        """Run `run`'s learner alone: a BatchedMADDPG holding its weights, targets, Adam
        state and update count (copies; for checkpoints and evaluation elsewhere)."""
        one = BatchedMADDPG(self.agents, self.specs[run], device=self.device)
        sl = slice(run * self.n, (run + 1) * self.n)
        pairs = (
            (self.actor.params, one.actor.params),
            (self.actor.targets, one.actor.targets),
            (self.critic.params, one.critic.params),
            (self.critic.targets, one.critic.targets),
        )
        with torch.no_grad():
            for src, dst in pairs:
                for s, d in zip(src, dst):
                    d.copy_(s[sl])
        for mine, theirs, params, their_params in (
            (self.actor_optim, one.actor_optim, self.actor.params, one.actor.params),
            (self.critic_optim, one.critic_optim, self.critic.params, one.critic.params),
        ):
            for p, q in zip(params, their_params):
                if p in mine.state:
                    st = mine.state[p]
                    theirs.state[q] = {
                        "step": st["step"].clone(),
                        "exp_avg": st["exp_avg"][sl].clone(),
                        "exp_avg_sq": st["exp_avg_sq"][sl].clone(),
                    }
        one.updates = self.updates
        return one

    def run_actor_weights(self, run: int) -> list[dict[str, torch.Tensor]]:
        """Run `run`'s actors as its learner alone gives them (`actor_weights`), read in
        place: what goes to the evaluator at every point, without copying the rest."""
        out = []
        for i, agent in enumerate(self.agents):
            e, d = run * self.n + i, agent.act_dim
            sd = {"scale": self.scale[e, 0, :d].clone(), "center": self.center[e, 0, :d].clone()}
            sd.update(self.actor.export(self.actor.params, e))
            out.append(sd)
        return out

    def load_run_actor_weights(self, run: int, weights: Sequence[dict[str, Any]]) -> None:
        """Run `run`'s actors from per-agent state dicts (`actor_weights`' format): an
        evaluator acting for a group's points at once."""
        for i, sd in enumerate(weights):
            self.actor.load(self.actor.params, run * self.n + i, sd)
        self.weights_changed()

    def run_state_dict(self, run: int) -> dict:
        """Run `run`'s checkpoint in the reference's format (what `macb train` writes)."""
        return self.run_learner(run).state_dict()

    def load_run_state_dicts(self, states: Sequence[dict]) -> None:
        """Every run's checkpoint at once (they must be at the same update: a group's runs
        update together)."""
        if len(states) != self.runs:
            raise ValueError(f"{len(states)} states for a group of {self.runs} runs")
        ones = []
        for spec, state in zip(self.specs, states):
            one = BatchedMADDPG(self.agents, spec, device=self.device)
            one.load_state_dict(state)
            ones.append(one)
        updates = {o.updates for o in ones}
        if len(updates) != 1:
            raise ValueError(f"the runs' checkpoints are at different updates: {sorted(updates)}")
        n = self.n
        with torch.no_grad():
            for run, one in enumerate(ones):
                sl = slice(run * n, (run + 1) * n)
                for dst, src in (
                    (self.actor.params, one.actor.params),
                    (self.actor.targets, one.actor.targets),
                    (self.critic.params, one.critic.params),
                    (self.critic.targets, one.critic.targets),
                ):
                    for d, s in zip(dst, src):
                        d[sl] = s
        for optim, params, name in (
            (self.actor_optim, self.actor.params, "actor_optim"),
            (self.critic_optim, self.critic.params, "critic_optim"),
        ):
            optim.state.clear()
            theirs = [(getattr(o, name), getattr(o, name.split("_")[0]).params) for o in ones]
            if not all(p[0] in o.state for o, p in theirs):
                continue
            for k, p in enumerate(params):
                first = theirs[0][0].state[theirs[0][1][k]]
                optim.state[p] = {
                    "step": first["step"].clone(),
                    "exp_avg": torch.cat([o.state[ps[k]]["exp_avg"] for o, ps in theirs]),
                    "exp_avg_sq": torch.cat([o.state[ps[k]]["exp_avg_sq"] for o, ps in theirs]),
                }
        self.updates = updates.pop()
        self.weights_changed()

    def state_dict(self) -> dict:
        """Refused with the per-run method's name, for a caller that takes a group for
        one learner (a group's state is its runs' states)."""
        raise TypeError("a group has one state per run: run_state_dict(run)")


def capture_update(
    learner: GroupMADDPG, inputs: Sequence[torch.Tensor], warmup: int = 3
) -> torch.cuda.CUDAGraph:
    """The update on fixed device `inputs` captured as one CUDA graph: warmed up on a
    side stream first, as capture needs; each `replay()` updates again from whatever
    the inputs hold then. CUDA only; docs/performance.md, 'On a GPU', says how to probe
    what it saves."""
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(warmup):
            learner.update(*inputs)
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        learner.update(*inputs)
    return graph
