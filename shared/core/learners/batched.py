"""The reference update (reference.py) with all agents batched into a few operations.

`BatchedMADDPG` computes what `MADDPG` computes (same networks, same critic step, actor
step and soft update in the same order, one shared minibatch) up to floating-point
rounding; tests/test_batched_equivalence.py checks it update by update. Why that holds:

* Within an update agents are independent: agent i's critic step touches only critic i,
  its actor step only actor i, and targets are read before any soft update. So all N
  critic steps are one step (one backward, one Adam call), then all N actor steps one
  step that reads the freshly updated critics, as the reference does. Adam is
  elementwise, so one Adam over stacked tensors equals N Adams over per-agent tensors.
* Agents of different sizes are zero-padded (layers.py). Padded inputs are always 0 and
  padded outputs never reach a loss, so their weights get exactly zero gradient, and
  Adam (m = v = 0, step 0 / (0 + eps) = 0) keeps them exactly zero.
* With lanes the minibatch is split into row blocks whose targets, forward and backward
  passes run at the same time in threads (lanes.py); their gradients are summed before
  each Adam step, which is the whole batch's gradient up to the order of additions.

Why it is faster: few, large operations whatever N (Adam's fused kernel called
directly, one `_foreach_lerp_` for all targets, one conversion of the losses), and no
autograd. A fixed lane count leaves `torch.set_num_threads` to the process and gives
bit-identical reruns. docs/performance.md, "Learner design and its measurements", has
the numbers.

`precision="bf16"` runs every matrix product (forward and backward, online and target
networks) on bf16 copies of the weights and activations, cast once per weight version
(`_weights`), with oneDNN's fp32 accumulation; master weights, gradients given to Adam,
Adam's moments, targets, the soft update, losses and `act` stay fp32. It changes the
arithmetic, not the algorithm: one update stays within bf16's rounding of the fp32 one
(tests/test_bf16.py). On a CPU without native bf16 the learner runs fp32 (precision.py).
In bf16 the master-weight work (Adam with the weights' bf16 copies, the soft update with
the targets') runs in fused.py's compiled kernel where a C compiler is at hand, with the
same results bit for bit; the copies then stay valid between updates, and every other
write to the weights (`load_state_dict`, `load_actor_weights`) marks them stale. In fp32
the same kernel runs each network's Adam step and its targets' soft update in one pass
(`adam_soft`): within `update` a network's targets are read again only by the next
update's target values, so they may follow its step at once; the same bits, one pass
over the weights less.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

import shared.core.learners.fused as fused_kernel
from shared.core.joint import offsets
from shared.core.learners.base import (
    AgentDims,
    LearnerSpec,
    Losses,
    check_agents,
    denormals_flushed,
)
from shared.core.learners.checkpoint import actor_state, export_state, import_state
from shared.core.learners.lanes import Lanes
from shared.core.learners.layers import Stack, mlp_backward, mlp_forward
from shared.core.learners.precision import DTYPES, resolve, resolve_device
from shared.core.transfer import send

if TYPE_CHECKING:  # annotations only
    from shared.core.learners.reference import MADDPG


#: An update's input: a host array, or a tensor on the learner's device already (a device
#: replay's gather, a graph-captured update's fixed inputs).
UpdateInput = np.ndarray | torch.Tensor  # (not replay.Batch, a sampled minibatch)


def stage(arrays: Sequence[UpdateInput], device: torch.device) -> list[torch.Tensor]:
    """Host arrays as fp32 tensors on an accelerator, in one non-blocking copy (`send`):
    one transfer per step, and nothing waits for it but the device's own queue. Tensors
    on the device already (a graph-captured update's inputs, a device replay's gather)
    are taken as they are."""
    on_device = [a for a in arrays if isinstance(a, torch.Tensor) and a.device.type == device.type]
    if len(on_device) == len(arrays):
        return [a.float() for a in on_device]
    return send([np.asarray(a, dtype=np.float32) for a in arrays], device)


def host_array(t: torch.Tensor) -> np.ndarray:
    """A result the caller reads on the host (`act`'s actions): on the CPU the tensor's
    own memory; from an accelerator one copy, the one wait for the device `act` has."""
    return t.numpy() if t.is_cpu else t.cpu().numpy()


class StackedMADDPG:
    """The batched MADDPG update over stacks of networks, in a layout its subclass gives.

    Everything an update computes lives here: the stacks and their initial weights,
    Adam over the stacked tensors, the targets, the critic and actor steps (in lanes or
    not), the soft update and the bf16 copies. How a batch maps onto the stack entries
    (`_per_agent`, `_joint_act`, `_critic_input`, `_target_q`) and which tensors the
    elementwise kernels take whole (`_parts`) is the layout: one run's N agents here and
    in `BatchedMADDPG`, R runs' R x N in `GroupMADDPG` (group.py). What a caller holds
    (acting, the per-run or per-learner state) is each subclass's own.
    """

    def __init__(
        self,
        agents: Sequence[AgentDims],
        spec: LearnerSpec,
        lanes: int = 1,
        precision: str = "fp32",
        fused: bool | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        check_agents(agents, spec)
        self.device = resolve_device(device)
        self.precision = resolve(precision, self.device)
        self.dtype = DTYPES[self.precision]  # of the matrix products
        self.agents = list(agents)
        self.spec = spec
        self.n = n = len(agents)
        self.centralized = spec.algo == "cen-maddpg"
        obs_dims = [a.obs_dim for a in agents]
        act_dims = [a.act_dim for a in agents]
        self.obs_off = offsets(obs_dims)
        self.act_off = offsets(act_dims)
        self.joint_obs, self.joint_act = self.obs_off[-1], self.act_off[-1]
        self.obs_pad, self.act_pad = max(obs_dims), max(act_dims)
        ar = torch.arange

        # Joint (B, joint) -> padded per-agent (N, B, pad): gather indices into the joint
        # vector with one zero column appended (index `joint`) for the padding.
        self._obs_idx = torch.full((n, self.obs_pad), self.joint_obs)
        self._act_idx = torch.full((n, self.act_pad), self.joint_act)
        for i in range(n):
            self._obs_idx[i, : obs_dims[i]] = ar(self.obs_off[i], self.obs_off[i + 1])
            self._act_idx[i, : act_dims[i]] = ar(self.act_off[i], self.act_off[i + 1])
        # Padded (N, B, act_pad) -> joint (B, joint_act): positions i * act_pad + k.
        self._joint_act_idx = torch.cat([i * self.act_pad + ar(d) for i, d in enumerate(act_dims)])

        actor_sizes = [self.obs_pad, *spec.hidden, self.act_pad]
        self.actor = Stack(n, actor_sizes, [ar(d) for d in obs_dims], [ar(d) for d in act_dims])
        if self.centralized:
            # Q_i(s, x): every critic reads cat(joint obs, joint act), width D.
            width = self.joint_obs + self.joint_act
            critic_in = [ar(width)] * n
            # In the actor step, critic i reads the batch's cat(s, x) with agent i's own
            # action columns replaced by mu_i(o_i) (thesis eq. 14-15): keep masks them out,
            # place_idx gathers a_i into them (index act_pad: an appended zero column),
            # own_cols reads dQ_i/da_i back out of dQ_i/d(input).
            self._keep = torch.ones(n, 1, width)
            self._place_idx = torch.full((n, 1, width), self.act_pad)
            self._own_cols = torch.zeros(n, 1, self.act_pad, dtype=torch.long)
            for i in range(n):
                cols = self.joint_obs + ar(self.act_off[i], self.act_off[i + 1])
                self._keep[i, 0, cols] = 0.0
                self._place_idx[i, 0, cols] = ar(act_dims[i])
                # Padded actions read column 0: harmless, their scale is 0 (see actor_step).
                self._own_cols[i, 0, : act_dims[i]] = cols
        else:
            # Q_i(o_i, a_i): cat(padded o_i, padded a_i).
            width = self.obs_pad + self.act_pad
            critic_in = [
                torch.cat([ar(o), self.obs_pad + ar(a)]) for o, a in zip(obs_dims, act_dims)
            ]
        self.critic = Stack(n, [width, *spec.hidden, 1], critic_in, [ar(1)] * n)

        # The reference Actor's buffers, stacked; 0 in padded columns, so padded actions
        # are exactly 0 and get no gradient.
        low = torch.zeros(n, 1, self.act_pad)
        high = torch.zeros(n, 1, self.act_pad)
        for i, a in enumerate(agents):
            low[i, 0, : a.act_dim] = torch.as_tensor(a.act_low, dtype=torch.float32)
            high[i, 0, : a.act_dim] = torch.as_tensor(a.act_high, dtype=torch.float32)
        self.scale = (high - low) / 2
        self.center = (high + low) / 2

        self._init_like_reference([len(c) for c in critic_in])
        self._stack_runs()
        self._place(self.device)  # built on the CPU, moved once
        self._make_optimizers()
        self.updates = 0
        if not isinstance(lanes, int):
            raise ValueError(
                f"lanes must be a positive int (for 'auto' wrap the learner in TunedMADDPG), "
                f"got {lanes!r}"
            )
        # Lanes are CPU threads: on an accelerator the device runs the rows in parallel.
        self.lanes = Lanes(lanes if self.device.type == "cpu" else 1)
        # The fused kernel (CPU only) and, in bf16, the weight lists whose copies it has
        # kept current since they were last cast; any other write to the weights empties it.
        if fused and self.device.type != "cpu":
            raise ValueError(f"fused needs the CPU (this learner runs on {self.device})")
        self._kernel = self._fused_kernel(fused) if self.device.type == "cpu" else None
        self._current: set[int] = set()
        # fp32 within `update`: whether an Adam step soft-updates its network's targets
        # (`adam_soft`), and the target lists it did so for since the last soft update.
        self._soft_in_step = False
        self._softened: set[int] = set()

    def _stack_runs(self) -> None:
        """Called once the stacks hold their initial weights, on the CPU, before they
        move to the device: a group lays its runs' stacks out here (group.py)."""

    def _place(self, device: torch.device) -> None:
        """Every tensor the update reads, on `device` (built on the CPU; a no-op there)."""
        for stack in (self.actor, self.critic):
            stack.params = [t.to(device) for t in stack.params]
            stack.targets = [t.to(device) for t in stack.targets]
        for name in (
            "_obs_idx", "_act_idx", "_joint_act_idx", "scale", "center",
            "_keep", "_place_idx", "_own_cols",
        ):  # fmt: skip
            if hasattr(self, name):
                setattr(self, name, getattr(self, name).to(device))

    @property
    def _flush(self) -> bool:
        """Whether an update flushes subnormals: a CPU setting (x86 DAZ/FTZ), so only
        there."""
        return self.spec.flush_denormals and self.device.type == "cpu"

    def _parts(self, tensors: Sequence[torch.Tensor]) -> list[torch.Tensor]:
        """The tensors as the elementwise passes take them: whole here. (A group gives
        some as one tensor per run, so that every element of a run takes the same
        vector-or-scalar path through the kernels as in the run's tensor alone.)"""
        return list(tensors)

    def _part_counts(self, tensors: Sequence[torch.Tensor]) -> list[int]:
        """How many parts `_parts` gives each tensor."""
        return [1] * len(tensors)

    def _make_optimizers(self) -> None:
        """Adam over the stacked tensors, and the weights' copies in the products' dtype.

        The optimizers hold the settings and state that state_dict() reads and writes
        (stepped by _step with a fused kernel). Per list of weights (online or target,
        actor or critic), the buffers its copies are cast into: none in fp32, where the
        products read the weights."""
        spec = self.spec
        self.actor_optim = torch.optim.Adam(self.actor.params, lr=spec.lr_actor, fused=True)
        self.critic_optim = torch.optim.Adam(self.critic.params, lr=spec.lr_critic, fused=True)
        self._low: dict[int, list[torch.Tensor]] = {}
        if self.dtype != torch.float32:
            actor, critic = self.actor, self.critic
            for tensors in (actor.params, actor.targets, critic.params, critic.targets):
                self._low[id(tensors)] = [torch.empty_like(t, dtype=self.dtype) for t in tensors]

    @staticmethod
    def _fused_kernel(fused: bool | None) -> fused_kernel.MasterKernel | None:
        if fused is False:
            return None
        found = fused_kernel.kernel()
        if fused and found is None:
            raise ValueError(
                "fused=True, but the fused kernel cannot be built here (see the log; "
                f"a C compiler as cc or $CC, and {fused_kernel.ENV_SWITCH} not off)"
            )
        return found

    def _weights(self, tensors: list[torch.Tensor]) -> list[torch.Tensor]:
        """One of the stacks' weight lists as the products read it: itself in fp32; in
        bf16 its copies, cast now (one `_foreach_copy_`). Called once per weight version
        an update uses (targets, critic before and after its step, actor), from the
        caller's thread, never in a lane, so lanes share the copies."""
        if self.dtype == torch.float32:
            return tensors
        low = self._low[id(tensors)]
        if id(tensors) in self._current:  # the fused kernel wrote them with the weights
            return low
        torch._foreach_copy_(low, tensors)
        if self._kernel is not None:  # from now on the kernel keeps them current
            self._current.add(id(tensors))
        return low

    def weights_changed(self) -> None:
        """Call after writing any weights other than through `update`: the bf16 copies
        are cast anew before their next use."""
        self._current.clear()

    def _low_x(self, x: torch.Tensor) -> torch.Tensor:
        """An input of a network's first layer in the products' dtype (fp32: x itself)."""
        return x.to(self.dtype)

    def _init_like_reference(self, critic_in: Sequence[int]) -> None:
        """The reference's initial weights for this seed: the same nn.Linear calls in order."""
        stacks = (
            (self.actor, [a.obs_dim for a in self.agents], [a.act_dim for a in self.agents]),
            (self.critic, critic_in, [1] * self.n),
        )

        def init(stack: Stack, i: int, fan_in: int, fan_out: int) -> None:
            sizes = [fan_in, *self.spec.hidden, fan_out]
            sd = {}
            for layer, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
                lin = torch.nn.Linear(a, b)
                sd[stack.key(layer, False)] = lin.weight.detach()
                sd[stack.key(layer, True)] = lin.bias.detach()
            stack.load(stack.params, i, sd)
            stack.load(stack.targets, i, sd)

        with torch.random.fork_rng(devices=[]):  # leave the caller's RNG stream alone
            torch.manual_seed(self.spec.seed)
            if self.spec.same_init:  # the reference's order: per agent, reseeded
                for i in range(self.n):
                    torch.manual_seed(self.spec.seed)
                    for stack, ins, outs in stacks:
                        init(stack, i, ins[i], outs[i])
                return
            for stack, ins, outs in stacks:
                for i in range(self.n):
                    init(stack, i, ins[i], outs[i])

    # ------------------------------------------------------------------ acting
    def _per_agent(self, joint: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """(B, joint) -> (N, B, pad): each agent's block, zero-padded. From one minibatch
        per agent, (N, B, joint), agent i's block of batch i."""
        padded = torch.nn.functional.pad(joint, (0, 1))
        if joint.dim() == 3:
            return torch.gather(padded, 2, idx[:, None, :].expand(-1, joint.shape[1], -1))
        # Contiguous, as a group's are: a product's rounding may depend on its input's
        # layout (seen with 3 rows), and a run alone must compute what it does in a group.
        return padded[:, idx].transpose(0, 1).contiguous()

    def _joint_act(self, per_agent: torch.Tensor) -> torch.Tensor:
        """(N, B, act_pad) -> (B, joint_act)."""
        return per_agent.transpose(0, 1).reshape(per_agent.shape[1], -1)[:, self._joint_act_idx]

    def _squash(self, out: torch.Tensor) -> torch.Tensor:
        """The actor's tanh output rescaled into each agent's box [low, high]."""
        return torch.addcmul(self.center, self.scale, out)

    # ----------------------------------------------------------------- learning
    def tensors(self, *arrays: UpdateInput) -> list[torch.Tensor]:
        """The arrays as fp32 tensors on the device: on the CPU the arrays themselves
        where they are fp32 already; elsewhere `stage`d, in one non-blocking copy."""
        if self.device.type != "cpu":
            return stage(arrays, self.device)
        return [torch.as_tensor(a, dtype=torch.float32, device=self.device) for a in arrays]

    def _critic_input(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """What the critics read: cat(s, x) (B, D) shared by all (Cen), or (N, B, D) own."""
        if self.centralized:
            return torch.cat([obs, act], -1)
        return torch.cat(
            [self._per_agent(obs, self._obs_idx), self._per_agent(act, self._act_idx)], -1
        )

    def target_q(self, rew: torch.Tensor, next_obs: torch.Tensor, done: torch.Tensor):
        """y_i = r_i + gamma (1 - done) Qbar_i(s', mubar_1(o'_1), ..., mubar_N(o'_N)): (N, B).

        With one minibatch per agent (next_obs (N, B, joint), rew (N, B, N), done (N, B))
        y_i is computed on batch i: Cen critics then need every agent's target action on
        every batch (one product over N x B rows), Dis critics only agent i's on batch i.
        """
        return self._target_q(self._target_weights(), rew, next_obs, done)

    def _target_weights(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """The target actors' and critics' weights as the products read them."""
        return self._weights(self.actor.targets), self._weights(self.critic.targets)

    def _mu(self, actor: Sequence[torch.Tensor], obs_pad: torch.Tensor) -> torch.Tensor:
        """Actions (N, rows, act_pad) of actors with these weights, in fp32."""
        return self._squash(torch.tanh(mlp_forward(actor, self._low_x(obs_pad))[-1].float()))

    def _q(self, critic: Sequence[torch.Tensor], q_in: torch.Tensor) -> torch.Tensor:
        """Q values (N, rows) of critics with these weights, in fp32."""
        return mlp_forward(critic, self._low_x(q_in))[-1].squeeze(-1).float()

    def _target_q(
        self,
        weights: tuple[list[torch.Tensor], list[torch.Tensor]],
        rew: torch.Tensor,
        next_obs: torch.Tensor,
        done: torch.Tensor,
    ) -> torch.Tensor:
        """`target_q` with the targets' weights given (`_target_weights`)."""
        actor, critic = weights
        if next_obs.dim() == 3:
            return self._target_q_per_agent(actor, critic, rew, next_obs, done)
        next_obs_pad = self._per_agent(next_obs, self._obs_idx)
        next_act = self._mu(actor, next_obs_pad)
        if self.centralized:
            q_in = torch.cat([next_obs, self._joint_act(next_act)], -1)
        else:
            q_in = torch.cat([next_obs_pad, next_act], -1)
        qf_next_target = self._q(critic, q_in)
        # done is (B,); reshape so a (B, 1) done cannot broadcast y to (N, B, B).
        return rew.T + self.spec.gamma * (1.0 - done.reshape(1, -1)) * qf_next_target

    def _target_q_per_agent(
        self,
        actor: list[torch.Tensor],
        critic: list[torch.Tensor],
        rew: torch.Tensor,
        next_obs: torch.Tensor,
        done: torch.Tensor,
    ) -> torch.Tensor:
        n, rows = next_obs.shape[:2]
        if self.centralized:
            every = self._mu(actor, self._per_agent(next_obs.reshape(n * rows, -1), self._obs_idx))
            q_in = torch.cat([next_obs, self._joint_act(every).reshape(n, rows, -1)], -1)
        else:
            own = self._per_agent(next_obs, self._obs_idx)
            q_in = torch.cat([own, self._mu(actor, own)], -1)
        qf_next_target = self._q(critic, q_in)
        agents = torch.arange(n, device=rew.device)
        return rew[agents, :, agents] + self.spec.gamma * (1.0 - done) * qf_next_target

    def _critic_grads(
        self,
        critic: list[torch.Tensor],
        obs: torch.Tensor,
        act: torch.Tensor,
        next_q_value: torch.Tensor,
        batch: int,
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Summed squared errors (N,) of these rows and their fp32 gradients, as parts of
        mean((Q_i - y_i)^2) over a minibatch of `batch` rows; `critic`: the critics'
        weights as the products read them."""
        acts = mlp_forward(critic, self._low_x(self._critic_input(obs, act)))
        diff = acts[-1].squeeze(-1).float() - next_q_value
        grad = diff.mul(2.0 / batch).unsqueeze(-1).to(self.dtype)  # d qf_loss_i / d Q_i
        grads, _ = mlp_backward(
            critic, acts, grad, True, False, torch.float32, self._low_grads(batch, obs)
        )
        assert grads is not None  # (asked for: `weights`)
        return diff.square().sum(1), grads

    def critic_step(
        self, obs: torch.Tensor, act: torch.Tensor, next_q_value: torch.Tensor
    ) -> torch.Tensor:
        """One Adam step of every critic on mean((Q_i - y_i)^2); returns the (N,) losses."""
        batch = obs.shape[-2]
        critic = self._weights(self.critic.params)
        sq_sum, grads = self._critic_grads(critic, obs, act, next_q_value, batch)
        self._step(self.critic_optim, self.critic.params, grads, self.critic.targets)
        return sq_sum / batch

    def _actor_weights(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """The actors' and (just updated) critics' weights as the actor step's products
        read them."""
        return self._weights(self.actor.params), self._weights(self.critic.params)

    def _actor_grads(
        self,
        weights: tuple[list[torch.Tensor], list[torch.Tensor]],
        obs: torch.Tensor,
        act: torch.Tensor,
        batch: int,
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Summed Q_i(.., mu_i(o_i), ..) (N,) of these rows and the fp32 gradients of
        -mean(Q_i) over a minibatch of `batch` rows with respect to actor i; `weights`
        from `_actor_weights`."""
        actor, critic = weights
        obs_pad = self._per_agent(obs, self._obs_idx)
        acts = mlp_forward(actor, self._low_x(obs_pad))
        tanh_out = torch.tanh(acts[-1].float())
        a = self._squash(tanh_out)  # (N, rows, act_pad)
        rows = a.shape[1]
        if self.centralized:
            placed = torch.gather(
                torch.nn.functional.pad(a, (0, 1)), 2, self._place_idx.expand(-1, rows, -1)
            )
            q_in = self._critic_input(obs, act) * self._keep + placed
        else:
            q_in = torch.cat([obs_pad, a], -1)
        critic_acts = mlp_forward(critic, self._low_x(q_in))
        # d actor_loss_i / d Q_i (in bf16 -1/B is off by < 2^-9: a scale Adam divides out)
        grad_q = torch.full_like(critic_acts[-1], -1.0 / batch)
        _, grad_in = mlp_backward(critic, critic_acts, grad_q, False, True)
        assert grad_in is not None  # asked for (`inputs`)
        if self.centralized:
            grad_a = torch.gather(grad_in, 2, self._own_cols.expand(-1, rows, -1))
        else:
            grad_a = grad_in[..., self.obs_pad :]
        # Through a = center + scale * tanh(out); scale is 0 in padded columns.
        grad_out = torch.ops.aten.tanh_backward(grad_a.float() * self.scale, tanh_out)
        grads, _ = mlp_backward(
            actor,
            acts,
            grad_out.to(self.dtype),
            True,
            False,
            torch.float32,
            self._low_grads(batch, obs),
        )
        q_sum = critic_acts[-1].squeeze(-1).sum(1, dtype=torch.float32)
        assert grads is not None  # (asked for: `weights`)
        return q_sum, grads

    def actor_step(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """One Adam step of every actor on -mean(Q_i(.., mu_i(o_i), ..)); returns (N,) losses.

        Critic i is the one just updated; the other agents' actions come from the batch
        (Cen). Only dQ_i/da_i is taken from the critic, never its weight gradients.
        """
        batch = obs.shape[-2]
        q_sum, grads = self._actor_grads(self._actor_weights(), obs, act, batch)
        self._step(self.actor_optim, self.actor.params, grads, self.actor.targets)
        return -q_sum / batch

    def _low_grads(self, batch: int, obs: torch.Tensor) -> bool:
        """Whether the weight gradients of these rows (`obs`) stay bf16 for the fused
        Adam: yes, unless they are a lane's block, whose gradients are summed with the
        other lanes' first (in fp32, as unfused: a bf16 sum would round)."""
        bf16 = self.dtype == torch.bfloat16
        return self._kernel is not None and bf16 and obs.shape[-2] == batch

    def _step(
        self,
        optim: torch.optim.Adam,
        params: list[torch.Tensor],
        grads: Sequence[torch.Tensor],
        targets: list[torch.Tensor],
    ) -> None:
        """One Adam step of one network, as `optim.step()` with `grads` would take it, without
        Optimizer.step's per-call bookkeeping (hooks, grouping, state checks), which is a
        noticeable share of a whole update on small networks: torch's fused kernel, or
        fused.py's (the same bits): in bf16 with the weights' bf16 copies written in the
        same pass, in fp32 within `update` with the soft update of `targets`, the
        network's targets (`soft_update` then skips them). Settings outside the plain
        Adam the learner uses (amsgrad, weight decay) go through `optim.step()` itself."""
        group = optim.param_groups[0]
        if group["amsgrad"] or group["weight_decay"] or group["maximize"]:
            for p, g in zip(params, grads):
                p.grad = g
            optim.step()
            self._current.discard(id(params))
            return
        state = optim.state
        if params[0] not in state:  # first step: initialise state as Adam(fused=True) does
            for p in params:
                state[p] = {
                    "step": torch.zeros((), dtype=torch.float32, device=p.device),
                    "exp_avg": torch.zeros_like(p),
                    "exp_avg_sq": torch.zeros_like(p),
                }
        states = [state[p] for p in params]
        steps = [s["step"] for s in states]
        torch._foreach_add_(steps, 1)
        beta1, beta2 = group["betas"]
        exp_avgs = [s["exp_avg"] for s in states]
        exp_avg_sqs = [s["exp_avg_sq"] for s in states]
        part = self._parts
        if self._kernel is not None and self.dtype == torch.float32 and self._soft_in_step:
            self._kernel.adam_soft(
                part(params), part(grads), part(exp_avgs), part(exp_avg_sqs), part(targets),
                steps[0].item(), lr=group["lr"], beta1=beta1, beta2=beta2, eps=group["eps"],
                tau=self.spec.tau,
            )  # fmt: skip
            self._softened.add(id(targets))
            return
        if self._kernel is not None and self.dtype == torch.bfloat16:
            self._kernel.adam(
                part(params), part(grads), part(exp_avgs), part(exp_avg_sqs),
                part(self._low[id(params)]), steps[0].item(),
                lr=group["lr"], beta1=beta1, beta2=beta2, eps=group["eps"],
            )  # fmt: skip
            self._current.add(id(params))
            return
        torch._fused_adam_(
            part(params),
            part(grads),
            part(exp_avgs),
            part(exp_avg_sqs),
            [],
            [s for s, k in zip(steps, self._part_counts(params)) for _ in range(k)],
            amsgrad=False,
            lr=group["lr"],
            beta1=beta1,
            beta2=beta2,
            weight_decay=0.0,
            eps=group["eps"],
            maximize=False,
        )

    def update_on(
        self,
        lanes: int,
        obs: UpdateInput,
        act: UpdateInput,
        rew: UpdateInput,
        next_obs: UpdateInput,
        done: UpdateInput,
    ) -> Mapping[str, float]:
        """`update` on one lane or on all of them (`lanes` is 1 or `self.lanes.n`): what
        a tuner picks from update to update. The result is the same up to the order of
        floating-point additions. Nothing in it reads the device from the host: the
        inputs go in one non-blocking copy, the losses come back unread (`Losses`)."""
        if lanes not in (1, self.lanes.n):
            raise ValueError(f"lanes must be 1 or {self.lanes.n}, got {lanes!r}")
        obs_t, act_t, rew_t, next_t, done_t = self.tensors(obs, act, rew, next_obs, done)
        fp32_kernel = self._kernel is not None and self.dtype == torch.float32
        with denormals_flushed(self._flush):
            # fp32 with the kernel: each step soft-updates its targets (`_step`); what an
            # update cut short by an error did so for is forgotten, not skipped again.
            self._softened.clear()
            self._soft_in_step = fp32_kernel and 0 <= self.spec.tau < 0.5
            try:
                if lanes > 1 and obs_t.shape[-2] > 1:
                    critic_losses, actor_losses = self._update_in_lanes(
                        obs_t, act_t, rew_t, next_t, done_t
                    )
                else:
                    y = self.target_q(rew_t, next_t, done_t)
                    critic_losses = self.critic_step(obs_t, act_t, y)
                    actor_losses = self.actor_step(obs_t, act_t)
            finally:
                self._soft_in_step = False
            self.soft_update()
        self.updates += 1
        return Losses(torch.stack([critic_losses.mean(), actor_losses.mean()]))

    def stats(self) -> dict[str, float]:
        """The fixed lane count (a tuner reports its own picks, see tuning.py), and `bf16`:
        1 if the products run in bf16, 0 in fp32 (also when bf16 was asked for on a CPU
        without it)."""
        return {
            "lanes": float(self.lanes.n),
            "bf16": float(self.precision == "bf16"),
            "fused": float(self._kernel is not None),
        }

    def _update_in_lanes(
        self,
        obs: torch.Tensor,
        act: torch.Tensor,
        rew: torch.Tensor,
        next_obs: torch.Tensor,
        done: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """`critic_step` then `actor_step` with the minibatch split into row blocks, one
        per lane. A loss is a mean over rows, so its gradient is the sum of the blocks'
        gradients (each scaled by 1/B): summed, they are the whole batch's gradient up
        to the order of the additions, and one Adam step per network follows as before.
        Targets and both forward/backward passes run in the lanes; the two sums and the
        Adam steps between them run here."""
        batch = obs.shape[-2]
        per_agent = obs.dim() == 3  # rows are the second axis of every array then
        blocks = [
            tuple(t[:, rows] if per_agent else t[rows] for t in (obs, act, rew, next_obs, done))
            for rows in self.lanes.blocks(batch)
        ]

        # The weights' bf16 copies are cast here, once, and read by every lane.
        targets, critic = self._target_weights(), self._weights(self.critic.params)

        flush = self._flush  # in the lanes' threads too

        def critic_part(b: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, list[torch.Tensor]]:
            o, a, r, o2, d = b
            with denormals_flushed(flush):
                return self._critic_grads(critic, o, a, self._target_q(targets, r, o2, d), batch)

        def actor_part(b: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, list[torch.Tensor]]:
            with denormals_flushed(flush):
                return self._actor_grads(weights, b[0], b[1], batch)

        sq_sum, grads = self._sum_parts(self.lanes.map(critic_part, blocks))
        self._step(self.critic_optim, self.critic.params, grads, self.critic.targets)
        weights = self._actor_weights()
        q_sum, grads = self._sum_parts(self.lanes.map(actor_part, blocks))
        self._step(self.actor_optim, self.actor.params, grads, self.actor.targets)
        return sq_sum / batch, -q_sum / batch

    @staticmethod
    def _sum_parts(
        parts: Sequence[tuple[torch.Tensor, list[torch.Tensor]]],
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        total, grads = parts[0]
        for part_total, part_grads in parts[1:]:
            total = total + part_total
            torch._foreach_add_(grads, part_grads)
        return total, grads

    def soft_update(self) -> None:
        """theta' <- tau theta + (1 - tau) theta' for every target network, in one call
        (fused: with the targets' bf16 copies), but those the fp32 Adam step soft-updated
        in this update already (`_step`)."""
        actor, critic, part = self.actor, self.critic, self._parts
        if self._softened:
            pending = [s for s in (actor, critic) if id(s.targets) not in self._softened]
            self._softened.clear()
            if pending:
                torch._foreach_lerp_(
                    part([t for s in pending for t in s.targets]),
                    part([p for s in pending for p in s.params]),
                    self.spec.tau,
                )
            return
        if self._kernel is not None and self.dtype == torch.bfloat16 and self.spec.tau < 0.5:
            self._kernel.soft_update(
                part(actor.targets + critic.targets),
                part(actor.params + critic.params),
                part(self._low[id(actor.targets)] + self._low[id(critic.targets)]),
                self.spec.tau,
            )
            self._current.update((id(actor.targets), id(critic.targets)))
            return
        torch._foreach_lerp_(
            part(actor.targets + critic.targets), part(actor.params + critic.params), self.spec.tau
        )
        self._current.difference_update((id(actor.targets), id(critic.targets)))


class BatchedMADDPG(StackedMADDPG):
    """Drop-in for the reference `MADDPG`: same constructor, results and checkpoints.

    The per-agent methods of the reference (`target_q(i, ...)`, `critic_step(i, ...)`,
    `actor_step(i, ...)`) are here for all agents at once and return (N, ...) tensors.
    `lanes` row blocks of each minibatch run in that many threads (`update`); a tuner
    may run an update on one of them instead (`update_on`, see tuning.py). `precision`
    is what the matrix products run in, fp32 or bf16 (`self.precision` says what they
    run in here: fp32 on a CPU without native bf16). `fused` (CPU only): None runs the
    master-weight work in fused.py's kernel where it builds, True insists on it (an error
    if it cannot be built), False keeps torch's ops; the results are the same.
    """

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Deterministic joint actions for joint observations (B, joint_obs) -> (B, joint_act)."""
        return host_array(self.act_on_device(obs))

    def act_on_device(self, obs: np.ndarray) -> torch.Tensor:
        """`act`'s actions as a tensor on the learner's device, not read from it."""
        (o,) = self.tensors(obs)
        lead = o.shape[:-1]
        o_pad = self._per_agent(o.reshape(-1, self.joint_obs), self._obs_idx)
        mu = self._squash(torch.tanh(mlp_forward(self.actor.params, o_pad)[-1]))
        return self._joint_act(mu).reshape(*lead, self.joint_act)

    def update(
        self,
        obs: UpdateInput,
        act: UpdateInput,
        rew: UpdateInput,
        next_obs: UpdateInput,
        done: UpdateInput,
    ) -> Mapping[str, float]:
        """One critic and one actor step for every agent, then soft target updates, on
        all of this learner's lanes.

        rew is (B, N): the extrinsic reward plus agent i's bonus in column i.
        """
        return self.update_on(self.lanes.n, obs, act, rew, next_obs, done)

    # ----------------------------------------------------------------- state
    def state_dict(self) -> dict:
        """The reference's format, tensors and primitives only: loads with
        torch.load(weights_only=True) into either MADDPG or BatchedMADDPG."""
        return export_state(self)

    def load_state_dict(self, state: dict) -> None:
        import_state(self, state)
        self.weights_changed()

    @classmethod
    def from_reference(cls, ref: MADDPG) -> BatchedMADDPG:
        """A batched copy of a reference learner: weights, targets, Adam states, counter."""
        m = cls(ref.agents, ref.spec)
        m.load_state_dict(ref.state_dict())
        return m

    def actor_weights(self) -> list[dict[str, torch.Tensor]]:
        """Per agent, a state dict for shared.core.networks.Actor (fresh tensors, safe to ship)."""
        return [actor_state(self, self.actor.params, i) for i in range(self.n)]

    def load_actor_weights(self, weights: Sequence[dict[str, Any]]) -> None:
        for i, sd in enumerate(weights):
            self.actor.load(self.actor.params, i, sd)
        self.weights_changed()
