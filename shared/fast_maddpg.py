"""The reference update of shared/maddpg.py with all agents batched into a few operations.

`BatchedMADDPG` computes what `MADDPG` computes (same networks, same critic step, actor
step and soft update in the same order, one shared minibatch) up to floating-point
rounding; tests/test_batched_equivalence.py checks it update by update. Why it is faster:

* Weights are stacked per layer, W (N, out, in) as nn.Linear stores them and b (N, 1, out),
  so one layer of all N agents is one `torch.baddbmm`. Agents with different observation
  or action sizes are zero-padded to the largest. Padded inputs are always 0 and padded
  outputs never reach a loss, so their weights get exactly zero gradient, and Adam
  (m = v = 0, step 0 / (0 + eps) = 0) keeps them exactly zero.
* Within an update agents are independent: agent i's critic step touches only critic i,
  its actor step only actor i, and targets are read before any soft update. So all N
  critic steps are one step (one backward, one Adam call), then all N actor steps one
  step that reads the freshly updated critics, as the reference does. Adam is
  elementwise, so one Adam over stacked tensors equals N Adams over per-agent tensors.
* Gradients are written out by hand (`mlp_backward`) instead of autograd. That removes
  the autograd engine's per-node cost, and computes exactly the gradients the algorithm
  uses: no critic weight gradients in the actor step (only dQ_i/da_i), no gradients for
  targets or batch inputs, no input gradient at an actor's first layer.
* Each matrix product runs in the layout the CPU BLAS (MKL) is fastest at on one core
  (see the layer functions below). The reference recomputes all N target actors once
  per agent; this does it once.
* Python overhead is a fixed ~100 tensor operations per update whatever N: Adam runs
  the fused kernel directly (`_adam_step`), targets move in one `_foreach_lerp_`, and
  the losses become floats in one conversion at the end.
* With `lanes=2` the minibatch is split into two row blocks whose targets, forward and
  backward passes run at the same time in two threads (`shared.lanes`); their
  gradients are summed before each Adam step, which is the whole batch's gradient up to
  the order of additions.
* With `lanes="auto"` (the platform's default) a `LaneTuner` picks, block by block of
  updates, the fastest of: one thread; two lanes; one lane with two torch intra-op
  threads; from measured update times. On an idle 2-core machine two threads win
  (torch's ~1.4x, lanes less: the lanes share the GIL); when other processes keep the
  cores busy, torch's spinning OpenMP threads run 2x-30x slower than one thread and
  lanes ~1.2x slower (a lane preempted while holding the GIL stalls the other), and the
  tuner falls back to one thread. A fixed lane count (and fixed `threads`) gives
  bit-identical reruns; "auto" gives reruns equal up to floating-point rounding.
* A caller that knows when other work runs beside it (the cluster's learner knows when
  the evaluator is evaluating the weights it just sent) passes `contended=True` for
  those updates; they get a tuner of their own, so the choice for the rest is not
  spoiled by their stalls, and during them the choice is what is fastest then (on 2
  cores: one thread, where two threads stall behind the evaluator's burst).

Threads: with a fixed lane count this module leaves `torch.set_num_threads` to the
process (lanes assume 1); with "auto" it sets it (1 or 2) for each block of updates.
benchmarks/bench_learner.py reports 1 thread, 2 threads, 2 lanes and a busy core.

`state_dict()` writes the reference's own per-agent format (module and Adam state dicts),
so checkpoints move between the two classes both ways, and a `BatchedMADDPG` built from
the same `LearnerSpec` starts from the reference's weights (the same seeded `nn.Linear`
initialisation, without reseeding the caller's global RNG).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from shared.lanes import Lanes, LaneTuner

if TYPE_CHECKING:  # annotations only: this module imports numpy and torch alone
    from shared.maddpg import MADDPG, AgentDims, LearnerSpec

ALGOS = ("ddpg", "dis-maddpg", "cen-maddpg")
# What lanes="auto" chooses among, as (lanes, torch intra-op threads).
AUTO_MODES = ((1, 1), (2, 1), (1, 2))


def _offsets(dims: Sequence[int]) -> list[int]:
    return [0, *np.cumsum(dims).tolist()]


# --------------------------------------------------------------------------- layers
# The three products of a stacked linear layer. MKL on one core is 3-10x slower for
# products with a narrow side (a last layer's 1-3 outputs, a first layer's 4-24 inputs)
# in some layouts, e.g. the ones `bmm`'s autograd picks; these pick the fast one. The
# floor in benchmarks/bench_learner.py times these same functions.
def linear_forward(x: torch.Tensor, w: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """x W^T + b: x (N, B, in), W (N, out, in), b (N, 1, out) -> (N, B, out)."""
    return torch.baddbmm(b, x, w.mT)


def linear_grad_input(grad: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """dL/dx = grad W: grad (N, B, out), W (N, out, in) -> (N, B, in)."""
    if w.shape[2] < w.shape[1]:  # narrow input: (W^T grad^T)^T is faster
        return torch.bmm(w.mT, grad.mT).mT
    return torch.bmm(grad, w)


def linear_grad_weight(grad: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """dL/dW = grad^T x: grad (N, B, out), x (N, B, in) -> (N, out, in), contiguous."""
    if x.shape[2] < grad.shape[2]:  # narrow input: (x^T grad)^T is faster
        return torch.bmm(x.mT, grad).mT.contiguous()
    return torch.bmm(grad.mT, x)


def mlp_forward(params: Sequence[torch.Tensor], x: torch.Tensor) -> list[torch.Tensor]:
    """N MLPs at once (shared.networks.mlp: ReLU between layers, none after the last).

    params = [W0, b0, W1, b1, ...]; x is (N, B, in), or (B, in) when all N networks read
    the same input (Cen critics). Returns every layer's input and the output, [x, h1, ...,
    out], which is what `mlp_backward` needs.
    """
    n = params[0].shape[0]
    acts = [x.expand(n, -1, -1) if x.dim() == 2 else x]
    last = len(params) // 2 - 1
    for layer in range(last + 1):
        h = linear_forward(acts[-1], params[2 * layer], params[2 * layer + 1])
        acts.append(h.relu_() if layer < last else h)
    return acts


def mlp_backward(
    params: Sequence[torch.Tensor],
    acts: Sequence[torch.Tensor],
    grad: torch.Tensor,
    weights: bool,
    inputs: bool,
) -> tuple[list[torch.Tensor] | None, torch.Tensor | None]:
    """Backpropagate dL/d(output) through `mlp_forward`'s layers.

    Returns (gradients for params, or None unless `weights`; dL/dx, or None unless
    `inputs`). Nothing else is computed: the actor step asks its critic for dL/dx only.
    """
    layers = len(params) // 2
    grads: list[torch.Tensor] = [None] * len(params)  # type: ignore[list-item]
    for layer in reversed(range(layers)):
        x = acts[layer]
        if weights:
            grads[2 * layer] = linear_grad_weight(grad, x)
            grads[2 * layer + 1] = grad.sum(1, keepdim=True)
        if layer == 0 and not inputs:
            break
        grad = linear_grad_input(grad, params[2 * layer])
        if layer > 0:  # x = relu(previous pre-activation): pass grad where x > 0
            grad = torch.ops.aten.threshold_backward(grad, x, 0.0)
    return (grads if weights else None), (grad if inputs else None)


# --------------------------------------------------------------------------- storage
class _Stack:
    """One kind of network (actors or critics) of all N agents: online and target tensors.

    Knows where agent i's reference weights sit in the padded stack, so it converts to and
    from the reference's per-agent state dicts (`net.0.weight`, `net.0.bias`, ...).
    """

    def __init__(
        self,
        n: int,
        sizes: Sequence[int],
        agent_in: Sequence[torch.Tensor],
        agent_out: Sequence[torch.Tensor],
    ) -> None:
        self.params: list[torch.Tensor] = []
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
            self.params += [torch.zeros(n, fan_out, fan_in), torch.zeros(n, 1, fan_out)]
        self.targets = [p.clone() for p in self.params]
        # index[i][layer] = (input indices, output indices) of agent i's weight.
        hidden = [torch.arange(h) for h in sizes[1:-1]]
        self.index = [list(zip([agent_in[i], *hidden], [*hidden, agent_out[i]])) for i in range(n)]

    @staticmethod
    def key(layer: int, bias: bool) -> str:
        return f"net.{2 * layer}.{'bias' if bias else 'weight'}"

    def export(self, tensors: Sequence[torch.Tensor], i: int) -> dict[str, torch.Tensor]:
        """Agent i's part of `tensors` (params, targets or an Adam moment), as new tensors."""
        out = {}
        for layer, (ins, outs) in enumerate(self.index[i]):
            out[self.key(layer, False)] = tensors[2 * layer][i][outs[:, None], ins]
            out[self.key(layer, True)] = tensors[2 * layer + 1][i, 0, outs]
        return out

    def load(self, tensors: Sequence[torch.Tensor], i: int, sd: dict[str, Any]) -> None:
        for layer, (ins, outs) in enumerate(self.index[i]):
            tensors[2 * layer][i][outs[:, None], ins] = torch.as_tensor(sd[self.key(layer, False)])
            tensors[2 * layer + 1][i, 0, outs] = torch.as_tensor(sd[self.key(layer, True)])


class _ActorView:
    """Agent i's actor as the reference exposes it, for `learner.actors[i].state_dict()`."""

    def __init__(self, learner: BatchedMADDPG, i: int) -> None:
        self.learner, self.i = learner, i

    def state_dict(self) -> dict[str, torch.Tensor]:
        return self.learner._actor_sd(self.learner.actor.params, self.i)


# --------------------------------------------------------------------------- learner
class BatchedMADDPG:
    """Drop-in for `shared.maddpg.MADDPG`: same constructor, results and checkpoints.

    The per-agent methods of the reference (`target_q(i, ...)`, `critic_step(i, ...)`,
    `actor_step(i, ...)`) are here for all agents at once and return (N, ...) tensors.
    """

    def __init__(
        self, agents: Sequence[AgentDims], spec: LearnerSpec, lanes: int | str = 1
    ) -> None:
        if spec.algo not in ALGOS:
            raise ValueError(f"algo must be one of {ALGOS}, got {spec.algo!r}")
        if spec.algo == "ddpg" and len(agents) != 1:
            raise ValueError("ddpg trains one agent; use dis-maddpg or cen-maddpg")
        self.agents = list(agents)
        self.spec = spec
        self.n = n = len(agents)
        self.centralized = spec.algo == "cen-maddpg"
        obs_dims = [a.obs_dim for a in agents]
        act_dims = [a.act_dim for a in agents]
        self.obs_off = _offsets(obs_dims)
        self.act_off = _offsets(act_dims)
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
        self.actor = _Stack(n, actor_sizes, [ar(d) for d in obs_dims], [ar(d) for d in act_dims])
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
        self.critic = _Stack(n, [width, *spec.hidden, 1], critic_in, [ar(1)] * n)

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
        # Adam over the stacked tensors, stepped by _adam_step with the fused kernel. The
        # optimizers hold the settings and state that state_dict() reads and writes.
        self.actor_optim = torch.optim.Adam(self.actor.params, lr=spec.lr_actor, fused=True)
        self.critic_optim = torch.optim.Adam(self.critic.params, lr=spec.lr_critic, fused=True)
        self.updates = 0
        # "auto": a tuner picks (lanes, torch threads) per block of updates.
        auto = lanes == "auto"
        if not auto and not isinstance(lanes, int):
            raise ValueError(f"lanes must be a positive int or 'auto', got {lanes!r}")
        self.lanes = Lanes(2 if auto else lanes)
        # One tuner for ordinary updates, one for updates the caller marks contended.
        self.tuner: LaneTuner[tuple[int, int]] | None = LaneTuner(AUTO_MODES) if auto else None
        self.contended_tuner: LaneTuner[tuple[int, int]] | None = (
            LaneTuner(AUTO_MODES) if auto else None
        )

    def _init_like_reference(self, critic_in: Sequence[int]) -> None:
        """The reference's initial weights for this seed: the same nn.Linear calls in order."""
        with torch.random.fork_rng(devices=[]):  # leave the caller's RNG stream alone
            torch.manual_seed(self.spec.seed)
            for stack, ins, outs in (
                (self.actor, [a.obs_dim for a in self.agents], [a.act_dim for a in self.agents]),
                (self.critic, critic_in, [1] * self.n),
            ):
                for i in range(self.n):
                    sizes = [ins[i], *self.spec.hidden, outs[i]]
                    sd = {}
                    for layer, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
                        lin = torch.nn.Linear(fan_in, fan_out)
                        sd[stack.key(layer, False)] = lin.weight.detach()
                        sd[stack.key(layer, True)] = lin.bias.detach()
                    stack.load(stack.params, i, sd)
                    stack.load(stack.targets, i, sd)

    # ------------------------------------------------------------------ acting
    def obs_slice(self, joint: torch.Tensor, i: int) -> torch.Tensor:
        return joint[..., self.obs_off[i] : self.obs_off[i + 1]]

    def act_slice(self, joint: torch.Tensor, i: int) -> torch.Tensor:
        return joint[..., self.act_off[i] : self.act_off[i + 1]]

    @staticmethod
    def _per_agent(joint: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """(B, joint) -> (N, B, pad): each agent's block, zero-padded."""
        return torch.nn.functional.pad(joint, (0, 1))[:, idx].transpose(0, 1)

    def _joint_act(self, per_agent: torch.Tensor) -> torch.Tensor:
        """(N, B, act_pad) -> (B, joint_act)."""
        return per_agent.transpose(0, 1).reshape(per_agent.shape[1], -1)[:, self._joint_act_idx]

    def _squash(self, out: torch.Tensor) -> torch.Tensor:
        """The actor's tanh output rescaled into each agent's box [low, high]."""
        return torch.addcmul(self.center, self.scale, out)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Deterministic joint actions for joint observations (B, joint_obs) -> (B, joint_act)."""
        o = torch.as_tensor(obs, dtype=torch.float32)
        lead = o.shape[:-1]
        o_pad = self._per_agent(o.reshape(-1, self.joint_obs), self._obs_idx)
        mu = self._squash(torch.tanh(mlp_forward(self.actor.params, o_pad)[-1]))
        return self._joint_act(mu).reshape(*lead, self.joint_act).numpy()

    # ----------------------------------------------------------------- learning
    def tensors(self, *arrays: np.ndarray) -> list[torch.Tensor]:
        return [torch.as_tensor(a, dtype=torch.float32) for a in arrays]

    def _critic_input(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """What the critics read: cat(s, x) (B, D) shared by all (Cen), or (N, B, D) own."""
        if self.centralized:
            return torch.cat([obs, act], -1)
        return torch.cat(
            [self._per_agent(obs, self._obs_idx), self._per_agent(act, self._act_idx)], -1
        )

    def target_q(self, rew: torch.Tensor, next_obs: torch.Tensor, done: torch.Tensor):
        """y_i = r_i + gamma (1 - done) Qbar_i(s', mubar_1(o'_1), ..., mubar_N(o'_N)): (N, B)."""
        next_obs_pad = self._per_agent(next_obs, self._obs_idx)
        next_act = self._squash(torch.tanh(mlp_forward(self.actor.targets, next_obs_pad)[-1]))
        if self.centralized:
            q_in = torch.cat([next_obs, self._joint_act(next_act)], -1)
        else:
            q_in = torch.cat([next_obs_pad, next_act], -1)
        qf_next_target = mlp_forward(self.critic.targets, q_in)[-1].squeeze(-1)
        # done is (B,); reshape so a (B, 1) done cannot broadcast y to (N, B, B).
        return rew.T + self.spec.gamma * (1.0 - done.reshape(1, -1)) * qf_next_target

    def _critic_grads(
        self, obs: torch.Tensor, act: torch.Tensor, next_q_value: torch.Tensor, batch: int
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Summed squared errors (N,) of these rows and their gradients, as parts of
        mean((Q_i - y_i)^2) over a minibatch of `batch` rows."""
        acts = mlp_forward(self.critic.params, self._critic_input(obs, act))
        diff = acts[-1].squeeze(-1) - next_q_value
        grad = diff.mul(2.0 / batch).unsqueeze(-1)  # d qf_loss_i / d Q_i
        grads, _ = mlp_backward(self.critic.params, acts, grad, weights=True, inputs=False)
        return diff.square().sum(1), grads  # type: ignore[return-value]

    def critic_step(
        self, obs: torch.Tensor, act: torch.Tensor, next_q_value: torch.Tensor
    ) -> torch.Tensor:
        """One Adam step of every critic on mean((Q_i - y_i)^2); returns the (N,) losses."""
        batch = obs.shape[0]
        sq_sum, grads = self._critic_grads(obs, act, next_q_value, batch)
        self._adam_step(self.critic_optim, self.critic.params, grads)
        return sq_sum / batch

    def _actor_grads(
        self, obs: torch.Tensor, act: torch.Tensor, batch: int
    ) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Summed Q_i(.., mu_i(o_i), ..) (N,) of these rows and the gradients of
        -mean(Q_i) over a minibatch of `batch` rows with respect to actor i."""
        obs_pad = self._per_agent(obs, self._obs_idx)
        acts = mlp_forward(self.actor.params, obs_pad)
        tanh_out = torch.tanh(acts[-1])
        a = self._squash(tanh_out)  # (N, rows, act_pad)
        rows = a.shape[1]
        if self.centralized:
            placed = torch.gather(
                torch.nn.functional.pad(a, (0, 1)), 2, self._place_idx.expand(-1, rows, -1)
            )
            q_in = torch.cat([obs, act], -1) * self._keep + placed
        else:
            q_in = torch.cat([obs_pad, a], -1)
        critic_acts = mlp_forward(self.critic.params, q_in)
        grad_q = torch.full_like(critic_acts[-1], -1.0 / batch)  # d actor_loss_i / d Q_i
        _, grad_in = mlp_backward(self.critic.params, critic_acts, grad_q, False, True)
        if self.centralized:
            grad_a = torch.gather(grad_in, 2, self._own_cols.expand(-1, rows, -1))
        else:
            grad_a = grad_in[..., self.obs_pad :]
        # Through a = center + scale * tanh(out); scale is 0 in padded columns.
        grad_out = torch.ops.aten.tanh_backward(grad_a * self.scale, tanh_out)
        grads, _ = mlp_backward(self.actor.params, acts, grad_out, weights=True, inputs=False)
        return critic_acts[-1].squeeze(-1).sum(1), grads  # type: ignore[return-value]

    def actor_step(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """One Adam step of every actor on -mean(Q_i(.., mu_i(o_i), ..)); returns (N,) losses.

        Critic i is the one just updated; the other agents' actions come from the batch
        (Cen). Only dQ_i/da_i is taken from the critic, never its weight gradients.
        """
        batch = obs.shape[0]
        q_sum, grads = self._actor_grads(obs, act, batch)
        self._adam_step(self.actor_optim, self.actor.params, grads)
        return -q_sum / batch

    @staticmethod
    def _adam_step(
        optim: torch.optim.Adam, params: Sequence[torch.Tensor], grads: Sequence[torch.Tensor]
    ) -> None:
        """`optim.step()` with `grads`: the same fused kernel, without Optimizer.step's
        per-call bookkeeping (hooks, grouping, state checks), which costs about 0.1 ms a
        call, a tenth of a whole update on small networks. Settings outside the plain Adam
        the learner uses (amsgrad, weight decay) go through `optim.step()` itself."""
        group = optim.param_groups[0]
        if group["amsgrad"] or group["weight_decay"] or group["maximize"]:
            for p, g in zip(params, grads):
                p.grad = g
            optim.step()
            return
        state = optim.state
        if params[0] not in state:  # first step: initialise state as Adam(fused=True) does
            for p in params:
                state[p] = {
                    "step": torch.zeros((), dtype=torch.float32),
                    "exp_avg": torch.zeros_like(p),
                    "exp_avg_sq": torch.zeros_like(p),
                }
        states = [state[p] for p in params]
        steps = [s["step"] for s in states]
        torch._foreach_add_(steps, 1)
        beta1, beta2 = group["betas"]
        torch._fused_adam_(
            list(params),
            list(grads),
            [s["exp_avg"] for s in states],
            [s["exp_avg_sq"] for s in states],
            [],
            steps,
            amsgrad=False,
            lr=group["lr"],
            beta1=beta1,
            beta2=beta2,
            weight_decay=0.0,
            eps=group["eps"],
            maximize=False,
        )

    def update(
        self,
        obs: np.ndarray,
        act: np.ndarray,
        rew: np.ndarray,
        next_obs: np.ndarray,
        done: np.ndarray,
        contended: bool = False,
    ) -> dict[str, float]:
        """One critic and one actor step for every agent, then soft target updates.

        rew is (B, N): the extrinsic reward plus agent i's bonus in column i.
        `contended`: other work known to run beside this update (with lanes="auto",
        its own tuner picks the threads; otherwise ignored). The result is the same.
        """
        t0 = time.perf_counter()
        obs_t, act_t, rew_t, next_t, done_t = self.tensors(obs, act, rew, next_obs, done)
        tuner = self.contended_tuner if contended else self.tuner
        if tuner is not None:
            lanes, threads = tuner.choose()
            if torch.get_num_threads() != threads:
                torch.set_num_threads(threads)
        else:
            lanes = self.lanes.n
        if lanes > 1 and obs_t.shape[0] > 1:
            critic_losses, actor_losses = self._update_in_lanes(obs_t, act_t, rew_t, next_t, done_t)
        else:
            y = self.target_q(rew_t, next_t, done_t)
            critic_losses = self.critic_step(obs_t, act_t, y)
            actor_losses = self.actor_step(obs_t, act_t)
        self.soft_update()
        self.updates += 1
        critic_loss, actor_loss = torch.stack([critic_losses.mean(), actor_losses.mean()]).tolist()
        if tuner is not None:
            tuner.record(time.perf_counter() - t0)
        return {"critic_loss": critic_loss, "actor_loss": actor_loss}

    def lane_stats(self) -> dict[str, float]:
        """Lanes in use: the fixed count, or the tuners' picks and measured times
        (`lanesAxB_*` for ordinary updates, `contended_lanesAxB_*` for contended ones,
        `contended_share` the share of updates that were contended)."""
        if self.tuner is None or self.contended_tuner is None:
            return {"lanes": float(self.lanes.n)}
        lanes, threads = self.tuner.current
        out = {"lanes": float(lanes), "threads": float(threads)}
        quiet = sum(self.tuner.chosen.values())
        contended = sum(self.contended_tuner.chosen.values())
        out["contended_share"] = contended / max(1, quiet + contended)
        for prefix, tuner in (("", self.tuner), ("contended_", self.contended_tuner)):
            total = max(1, sum(tuner.chosen.values()))
            for mode in tuner.options:
                name = f"{prefix}lanes{mode[0]}x{mode[1]}"  # lanes x torch threads
                out[f"{name}_share"] = tuner.chosen[mode] / total
                typical = tuner.estimate_s[mode]  # smoothed median update time
                out[f"{name}_update_ms"] = 1e3 * typical if typical is not None else 0.0
        return out

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
        batch = obs.shape[0]
        blocks = [
            tuple(t[rows] for t in (obs, act, rew, next_obs, done))
            for rows in self.lanes.blocks(batch)
        ]

        def critic_part(b: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, list[torch.Tensor]]:
            o, a, r, o2, d = b
            return self._critic_grads(o, a, self.target_q(r, o2, d), batch)

        sq_sum, grads = self._sum_parts(self.lanes.map(critic_part, blocks))
        self._adam_step(self.critic_optim, self.critic.params, grads)
        q_sum, grads = self._sum_parts(
            self.lanes.map(lambda b: self._actor_grads(b[0], b[1], batch), blocks)
        )
        self._adam_step(self.actor_optim, self.actor.params, grads)
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
        """theta' <- tau theta + (1 - tau) theta' for every target network, in one call."""
        torch._foreach_lerp_(
            self.actor.targets + self.critic.targets,
            self.actor.params + self.critic.params,
            self.spec.tau,
        )

    # ----------------------------------------------------------------- state
    def _actor_sd(self, tensors: Sequence[torch.Tensor], i: int) -> dict[str, torch.Tensor]:
        """Agent i's actor in shared.networks.Actor's state_dict layout (fresh tensors)."""
        d = self.agents[i].act_dim
        sd = {"scale": self.scale[i, 0, :d].clone(), "center": self.center[i, 0, :d].clone()}
        sd.update(self.actor.export(tensors, i))
        return sd

    def _optim_sds(self, optim: torch.optim.Adam, stack: _Stack) -> list[dict]:
        """Per-agent Adam state dicts, as the reference's per-agent optimizers write them."""
        group = {k: v for k, v in optim.param_groups[0].items() if k != "params"}
        group.update(foreach=None, fused=None, params=list(range(len(stack.params))))
        states = [optim.state.get(p, {}) for p in stack.params]
        # Per-element tensors shaped like the parameter (exp_avg, exp_avg_sq, and
        # max_exp_avg_sq with amsgrad); "step" is one scalar shared by all agents.
        keys = [k for k in states[0] if k != "step"]
        moments = {
            k: [stack.export([s[k] for s in states], i) for i in range(self.n)] for k in keys
        }
        out = []
        for i in range(self.n):
            state = {}
            if states[0]:
                for j, name in enumerate(stack.export(stack.params, i)):
                    state[j] = {"step": states[j]["step"].clone()}
                    state[j].update({k: moments[k][i][name] for k in keys})
            out.append({"state": state, "param_groups": [dict(group)]})
        return out

    def _load_optim(self, optim: torch.optim.Adam, stack: _Stack, sds: Sequence[dict]) -> None:
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
        step = torch.tensor(steps.pop(), dtype=torch.float32)
        for p in stack.params:
            optim.state[p] = {"step": step.clone()}
        for k in (k for k in sds[0]["state"][0] if k != "step"):
            moment = [torch.zeros_like(p) for p in stack.params]
            for i, sd in enumerate(sds):
                stack.load(moment, i, {name: sd["state"][j][k] for j, name in enumerate(names)})
            for p, m in zip(stack.params, moment):
                optim.state[p][k] = m

    def state_dict(self) -> dict:
        """The reference's format, tensors and primitives only: loads with
        torch.load(weights_only=True) into either MADDPG or BatchedMADDPG."""
        n = range(self.n)
        return {
            "algo": self.spec.algo,
            "updates": self.updates,
            "actors": [self._actor_sd(self.actor.params, i) for i in n],
            "critics": [self.critic.export(self.critic.params, i) for i in n],
            "actor_targets": [self._actor_sd(self.actor.targets, i) for i in n],
            "critic_targets": [self.critic.export(self.critic.targets, i) for i in n],
            "actor_optims": self._optim_sds(self.actor_optim, self.actor),
            "critic_optims": self._optim_sds(self.critic_optim, self.critic),
        }

    def load_state_dict(self, state: dict) -> None:
        if state["algo"] != self.spec.algo:
            raise ValueError(f"checkpoint is for {state['algo']}, learner is {self.spec.algo}")
        for key in ("actors", "critics", "actor_targets", "critic_targets"):
            if len(state[key]) != self.n:
                raise ValueError(f"checkpoint has {len(state[key])} {key}, learner has {self.n}")
        self.updates = int(state["updates"])
        for key, stack, tensors in (
            ("actors", self.actor, self.actor.params),
            ("actor_targets", self.actor, self.actor.targets),
            ("critics", self.critic, self.critic.params),
            ("critic_targets", self.critic, self.critic.targets),
        ):
            for i, sd in enumerate(state[key]):
                stack.load(tensors, i, sd)
        self._load_optim(self.actor_optim, self.actor, state["actor_optims"])
        self._load_optim(self.critic_optim, self.critic, state["critic_optims"])

    @classmethod
    def from_reference(cls, ref: MADDPG) -> BatchedMADDPG:
        """A batched copy of a reference learner: weights, targets, Adam states, counter."""
        m = cls(ref.agents, ref.spec)
        m.load_state_dict(ref.state_dict())
        return m

    def actor_weights(self) -> list[dict[str, torch.Tensor]]:
        """Per agent, a state dict for shared.networks.Actor (fresh tensors, safe to ship)."""
        return [self._actor_sd(self.actor.params, i) for i in range(self.n)]

    def load_actor_weights(self, weights: list[dict[str, Any]]) -> None:
        for i, sd in enumerate(weights):
            self.actor.load(self.actor.params, i, sd)

    @property
    def actors(self) -> list[_ActorView]:
        """Objects with the reference actors' `state_dict()` (for networks.actor_weights)."""
        return [_ActorView(self, i) for i in range(self.n)]
