"""N agents' MLPs as stacked tensors: the forward pass, its hand-written backward, and
the padded storage they run on.

Weights are stacked per layer, W (N, out, in) as nn.Linear stores them and b (N, 1, out),
so one layer of all N agents is one `torch.baddbmm`; agents with different observation
or action sizes are zero-padded to the largest. Gradients are written out by hand
instead of autograd: that saves the engine's per-node cost and computes only the
gradients the algorithm uses (none for targets or batch inputs, none for critic weights
in the actor step, no input gradient at an actor's first layer).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch


# The three products of a stacked linear layer. MKL on one core is several times slower for
# products with a narrow side (a last layer's 1-3 outputs, a first layer's 4-24 inputs)
# in some layouts, e.g. the ones `bmm`'s autograd picks; these pick the fast one. bf16
# products run in oneDNN, whose kernels are fastest in the plain layouts, so the layout
# trick is for fp32 only. The floor in benchmarks/bench_learner.py times these same
# functions. Both tricks, the layout and the stack of two below, are for the CPU's
# kernels and its bit-for-bit rule: on an accelerator every product takes the plain form.
def linear_forward(x: torch.Tensor, w: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """x W^T + b: x (N, B, in), W (N, out, in), b (N, 1, out) -> (N, B, out).

    A stack of one network with one output (DDPG's critic head) goes through torch's
    batched kernel as a stack of two (the same entry twice, not copied): alone, torch
    takes a matrix-vector path whose rounding differs, and a network's output would then
    depend on how many networks share its stack (a run alone vs. in a group)."""
    if w.shape[0] == 1 and w.shape[1] == 1 and w.is_cpu:
        two = (2, -1, -1)
        return torch.baddbmm(b.expand(two), x.expand(two), w.expand(two).mT)[:1]
    return torch.baddbmm(b, x, w.mT)


def linear_grad_input(grad: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """dL/dx = grad W: grad (N, B, out), W (N, out, in) -> (N, B, in)."""
    if w.shape[2] < w.shape[1] and w.dtype != torch.bfloat16 and w.is_cpu:  # narrow (MKL)
        return torch.bmm(w.mT, grad.mT).mT  # (W^T grad^T)^T is faster
    return torch.bmm(grad, w)


def linear_grad_weight(
    grad: torch.Tensor, x: torch.Tensor, dtype: torch.dtype | None = None
) -> torch.Tensor:
    """dL/dW = grad^T x: grad (N, B, out), x (N, B, in) -> (N, out, in), contiguous, in
    `dtype` (default the inputs'; a bf16 product's gradient goes to fp32 master weights).

    A stack of one network with one output (DDPG's critic head) goes through the batched
    kernel as a stack of two, as in `linear_forward`: alone, grad^T is one row and some
    CPUs (AVX-512 Xeons) take a vector path that sums the batch in another order."""
    if not grad.is_cpu:
        out = torch.bmm(grad.mT, x)
        return out if dtype is None else out.to(dtype)
    if grad.shape[0] == 1 and grad.shape[2] == 1:
        two = (2, -1, -1)
        out = torch.bmm(grad.expand(two).mT, x.expand(two))[:1]
        return out if dtype is None else out.to(dtype)
    if x.shape[2] < grad.shape[2] and x.dtype != torch.bfloat16:  # narrow input (MKL)
        out = torch.bmm(x.mT, grad).mT.contiguous()  # (x^T grad)^T is faster
    else:
        out = torch.bmm(grad.mT, x)
    return out if dtype is None else out.to(dtype)


# ReLU and its backward. torch's bf16 kernels for both take several times their fp32 time,
# more than a whole first-layer product; bf16's int16 view does the same work in integer
# kernels. bf16 is sign and magnitude: a value is below +0 exactly when its bits as an
# int16 are, so clamping those at 0 is ReLU for every value but a NaN with the sign bit
# set (which becomes 0 instead of staying NaN). CPU only: an accelerator's bf16 ReLU is
# its own fast kernel.
def relu_(h: torch.Tensor) -> torch.Tensor:
    """h.relu_(), in place; bf16 on the CPU through its int16 view."""
    if h.dtype == torch.bfloat16 and h.is_cpu:
        h.view(torch.int16).clamp_min_(0)
        return h
    return h.relu_()


def relu_backward(grad: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """dL/d(pre-activation) from dL/dx, x a `relu_` output: grad where x > 0, else 0.

    bf16: x's int16 bits are >= 0, and 0 only for +0, so clamped at 1 they are the 0/1
    mask, and the int16 product keeps or zeroes grad's bits (a positive NaN in x passes
    grad, where threshold_backward would zero it)."""
    if grad.dtype == torch.bfloat16 and x.dtype == torch.bfloat16 and grad.is_cpu:
        mask = x.view(torch.int16).clamp_max(1)
        return torch.mul(grad.view(torch.int16), mask).view(torch.bfloat16)
    return torch.ops.aten.threshold_backward(grad, x, 0.0)


def mlp_forward(params: Sequence[torch.Tensor], x: torch.Tensor) -> list[torch.Tensor]:
    """N MLPs at once (shared.core.networks.mlp: ReLU between layers, none after the last).

    params = [W0, b0, W1, b1, ...]; x is (N, B, in), or (B, in) when all N networks read
    the same input (Cen critics). Returns every layer's input and the output, [x, h1, ...,
    out], which is what `mlp_backward` needs.
    """
    n = params[0].shape[0]
    acts = [x.expand(n, -1, -1) if x.dim() == 2 else x]
    last = len(params) // 2 - 1
    for layer in range(last + 1):
        h = linear_forward(acts[-1], params[2 * layer], params[2 * layer + 1])
        acts.append(relu_(h) if layer < last else h)
    return acts


def mlp_backward(
    params: Sequence[torch.Tensor],
    acts: Sequence[torch.Tensor],
    grad: torch.Tensor,
    weights: bool,
    inputs: bool,
    grad_dtype: torch.dtype | None = None,
    low_weight_grads: bool = False,
) -> tuple[list[torch.Tensor] | None, torch.Tensor | None]:
    """Backpropagate dL/d(output) through `mlp_forward`'s layers.

    Returns (gradients for params, or None unless `weights`; dL/dx, or None unless
    `inputs`). Nothing else is computed: the actor step asks its critic for dL/dx only.
    The params' gradients are in `grad_dtype` (default the params'): products run in the
    params' dtype (bf16 copies), gradients go to fp32 master weights, and bias gradients,
    sums over the batch, are summed in that dtype. `low_weight_grads` leaves the weight
    gradients in the products' dtype, as the products round them anyway (the fused Adam,
    fused.py, reads bf16 gradients: the same values without a conversion pass).
    """
    layers = len(params) // 2
    # (every slot is filled below when `weights`; the list is returned only then)
    grads: list[torch.Tensor] = [None] * len(params)  # type: ignore[list-item]
    for layer in reversed(range(layers)):
        x = acts[layer]
        if weights:
            grads[2 * layer] = linear_grad_weight(grad, x, None if low_weight_grads else grad_dtype)
            grads[2 * layer + 1] = grad.sum(1, keepdim=True, dtype=grad_dtype)
        if layer == 0 and not inputs:
            break
        grad = linear_grad_input(grad, params[2 * layer])
        if layer > 0:  # x = relu(previous pre-activation): pass grad where x > 0
            grad = relu_backward(grad, x)
    return (grads if weights else None), (grad if inputs else None)


class Stack:
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
        """Agent i's per-agent state dict `sd` written into its place in `tensors`."""
        for layer, (ins, outs) in enumerate(self.index[i]):
            w, b = tensors[2 * layer], tensors[2 * layer + 1]
            w[i][outs[:, None], ins] = torch.as_tensor(sd[self.key(layer, False)], device=w.device)
            b[i, 0, outs] = torch.as_tensor(sd[self.key(layer, True)], device=b.device)
