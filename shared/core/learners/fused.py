"""The learners' master-weight work (Adam, the soft update, the weights' bf16 copies)
in one pass over the weights each, from a small C kernel (master.c) compiled on first use.

Why: in a bf16 update the matrix products are several times cheaper than in fp32, and what
is left is mostly memory traffic over the ~0.5 M fp32 master weights: torch's fused Adam
(reads weight, gradient and both moments, writes three), `_foreach_lerp_` for the targets,
five `_foreach_copy_` casts to bf16 copies and the gradients' bf16 -> fp32 conversions,
each a pass of its own. torch has no op doing them together. The kernel's Adam reads bf16
gradients as they come out of the products and writes the weight's bf16 copy in the same
pass, its soft update writes the target's copy, so no cast pass is left (the copies stay
valid from one update to the next; `BatchedMADDPG` re-casts them after any other write to
the weights). The arithmetic is torch's, operation for operation: the results equal the
unfused bf16 path's bit for bit (tests/test_fused.py), so `fused` changes speed only.

An fp32 learner has no copies to keep, and its matrix products dominate, but on a
2-core machine running two learners its elementwise passes are memory-bound: Adam reads
every weight, its gradient and both moments and writes three, then `_foreach_lerp_`
reads every weight again with its target and writes the target. The kernel's
`adam_soft` does both in one pass (the weight is at hand when its target is updated),
with the same arithmetic (torch's Adam, then torch's lerp): the same bits, one pass less.

The kernel is built with the system C compiler (`cc`, or $CC) into a cache directory
($MACB_KERNEL_CACHE, default ~/.cache/macb/kernels), named by a digest of the source, the
compiler's version and the flags, so a rebuilt or changed compiler gets its own file and
concurrent processes never see a half-written one (written under a temporary name, then
renamed). Where no compiler works (a slim container image), `kernel()` returns None, says
why once in the log, and the learner runs the unfused torch path: same numbers, slower.
`-march=native` is right because the file is built where it runs. Threads: OpenMP, as many
as torch's intra-op setting (which the learner's tuner switches), on a large tensor. The
kernel is linked against libgomp.so.1, the soname of the runtime torch's wheel carries and
has loaded already, so the loader binds it to torch's: one OpenMP runtime and one pool of
threads in the process (a pthread of the kernel's own ran the update slower on two
threads: torch's OpenMP worker spins on the other core between its ops). ctypes releases
the GIL while the kernel runs.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import logging
import math
import os
import shutil
import subprocess
import tempfile
from collections.abc import Sequence
from pathlib import Path

import torch

log = logging.getLogger("macb.learners")

SOURCE = Path(__file__).with_name("master.c")
FLAGS = (
    "-O3",
    "-march=native",
    "-ffp-contract=off",
    "-fno-math-errno",
    "-fopenmp",
    "-shared",
    "-fPIC",
)
# "0", "off", "false" or "no" turn the kernel off in every learner of the process.
ENV_SWITCH = "MACB_FUSED"

# Widths of torch's fused-Adam vector loop to try (fused.py's probe, master.c's `vec`).
VEC_WIDTHS = (8, 16, 4, 32)

_P = ctypes.POINTER
_ptrs = ctypes.c_void_p


def cache_dir() -> Path:
    return Path(os.environ.get("MACB_KERNEL_CACHE") or Path.home() / ".cache" / "macb" / "kernels")


def _compiler() -> str | None:
    cc = os.environ.get("CC") or "cc"
    return shutil.which(cc)


def _build(cc: str) -> Path:
    """The kernel's shared object for this source, compiler and flags: built once, cached."""
    version = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30).stdout
    digest = hashlib.sha256(
        SOURCE.read_bytes() + version.encode() + " ".join(FLAGS).encode()
    ).hexdigest()[:16]
    target = cache_dir() / f"master-{digest}.so"
    if target.exists():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        out = Path(tmp) / target.name
        done = subprocess.run(
            [cc, *FLAGS, "-o", str(out), str(SOURCE), "-lm"],
            capture_output=True,
            text=True,
            timeout=120,
        )
        if done.returncode != 0:
            raise RuntimeError(f"{cc} failed: {done.stderr.strip()[:500]}")
        os.replace(out, target)
    return target


def switched_off() -> bool:
    return os.environ.get(ENV_SWITCH, "").strip().lower() in ("0", "off", "false", "no")


@functools.cache
def kernel() -> MasterKernel | None:
    """The compiled kernel, or None (logged once) where it cannot be built or loaded, or
    where $MACB_FUSED turns it off. Also the way into torch's OpenMP threads for
    `flush_denormals` (base.py), in fp32 learners too."""
    if switched_off():
        log.info("%s is off: the learners' master weights go through torch's ops", ENV_SWITCH)
        return None
    cc = _compiler()
    if cc is None:
        log.warning(
            "no C compiler (cc or $CC) on PATH: a learner runs its master-weight work "
            "unfused (same results, slower), and flush_denormals reaches only the OpenMP "
            "threads an update starts (docs/performance.md, 'bf16: the fused master-weight "
            "pass', 'Subnormal Adam moments')"
        )
        return None
    try:
        found = MasterKernel(ctypes.CDLL(str(_build(cc))))
    except (OSError, RuntimeError, subprocess.SubprocessError) as err:
        log.warning(
            "the learners' fused kernel could not be built (%s): their master-weight "
            "work runs unfused (same results, slower)",
            err,
        )
        return None
    if found.vec is None:
        log.warning(
            "the learners' fused kernel does not reproduce this torch's Adam bit for bit "
            "(for no vector width in %s): its master-weight work runs unfused",
            VEC_WIDTHS,
        )
        return None
    if not found.lerp_matches:
        log.warning(
            "the learners' fused kernel does not reproduce this torch's lerp bit for bit: "
            "the master-weight work runs unfused"
        )
        return None
    return found


def _adam_scalars(step: float, lr: float, beta1: float, beta2: float, eps: float) -> tuple:
    """master.c's Adam scalars, computed as torch's kernel computes them (in double, then
    rounded to float by ctypes): beta1, beta2, 1 - beta1, 1 - beta2, the step size
    lr / (1 - beta1^step), sqrt(1 - beta2^step), eps. One place for both entry points."""
    bias_correction1 = 1 - beta1**step
    bias_correction2 = 1 - beta2**step
    return (
        beta1, beta2, 1 - beta1, 1 - beta2, lr / bias_correction1, math.sqrt(bias_correction2), eps
    )  # fmt: skip


def _array(tensors: Sequence[torch.Tensor]) -> ctypes.Array:
    return (_ptrs * len(tensors))(*[t.data_ptr() for t in tensors])


class MasterKernel:
    """master.c's entry points: Adam and the soft update over lists of contiguous CPU
    tensors, and the floating-point mode of torch's OpenMP threads."""

    def __init__(self, lib: ctypes.CDLL) -> None:
        f = ctypes.c_float
        i64 = ctypes.c_int64
        lib.macb_adam.restype = None
        lib.macb_adam.argtypes = [i64, _P(_ptrs), _P(_ptrs), _P(ctypes.c_int32), _P(_ptrs)]
        lib.macb_adam.argtypes += [_P(_ptrs), _P(_ptrs), _P(i64)]
        lib.macb_adam.argtypes += [f] * 7 + [ctypes.c_int32] * 2
        lib.macb_flush_denormals.restype = ctypes.c_int32
        lib.macb_flush_denormals.argtypes = [ctypes.c_int32, ctypes.c_int32]
        lib.macb_adam_soft.restype = None
        lib.macb_adam_soft.argtypes = [i64] + [_P(_ptrs)] * 5 + [_P(i64)]
        lib.macb_adam_soft.argtypes += [f] * 7 + [ctypes.c_int32, f, ctypes.c_int32]
        lib.macb_soft_update.restype = None
        lib.macb_soft_update.argtypes = [i64, _P(_ptrs), _P(_ptrs), _P(_ptrs), _P(i64), f]
        lib.macb_soft_update.argtypes += [ctypes.c_int32]
        self.lib = lib
        self.vec: int | None = 8  # the probe's first try; then what matched, or None
        self.vec = self._probe_vec()
        self.lerp_matches = self._probe_lerp()

    def _probe_vec(self) -> int | None:
        """The width of torch's vector loop in its fused Adam, found by running both on
        tensors whose every element-count between 1 and 47 puts elements on both sides of
        that loop's end: the width whose results equal torch's bit for bit, else None."""
        gen = torch.Generator().manual_seed(0)
        sizes = list(range(1, 48))

        def tensors() -> list[list[torch.Tensor]]:
            out = [[torch.randn(n, generator=gen) * 0.1 for n in sizes]]
            out.append([torch.randn(n, generator=gen) * 1e-2 for n in sizes])
            out.append([torch.randn(n, generator=gen) * 1e-3 for n in sizes])
            out.append([torch.rand(n, generator=gen) * 1e-4 for n in sizes])
            return out

        p, g, m, v = tensors()
        theirs = [[t.clone() for t in ts] for ts in (p, m, v)]
        torch._fused_adam_(
            theirs[0], g, theirs[1], theirs[2], [], [torch.tensor(3.0) for _ in sizes],
            amsgrad=False, lr=1e-3, beta1=0.9, beta2=0.999, weight_decay=0.0, eps=1e-8,
            maximize=False,
        )  # fmt: skip
        for vec in VEC_WIDTHS:
            self.vec = vec
            ours = [[t.clone() for t in ts] for ts in (p, m, v)]
            lows = [torch.empty(n, dtype=torch.bfloat16) for n in sizes]
            self.adam(ours[0], g, ours[1], ours[2], lows, 3.0, 1e-3, 0.9, 0.999, 1e-8)
            if all(torch.equal(a, b) for xs, ys in zip(ours, theirs) for a, b in zip(xs, ys)):
                return vec
        return None

    def _probe_lerp(self) -> bool:
        """Whether the soft update equals torch's lerp bit for bit on tensors of 1 to 47
        elements (both sides of its vector loop's end): the kernel computes it as one
        fused multiply-add, as torch's vector loop does."""
        gen = torch.Generator().manual_seed(1)
        sizes = list(range(1, 48))
        params = [torch.randn(n, generator=gen) for n in sizes]
        theirs = [p + 0.1 * torch.randn(n, generator=gen) for p, n in zip(params, sizes)]
        ours = [t.clone() for t in theirs]
        lows = [torch.empty(n, dtype=torch.bfloat16) for n in sizes]
        self.soft_update(ours, params, lows, 0.01)
        torch._foreach_lerp_(theirs, params, 0.01)
        return all(torch.equal(a, b) for a, b in zip(ours, theirs))

    def flush_denormals(self, on: bool, threads: int) -> bool:
        """DAZ and FTZ on (or off) in every thread of an OpenMP team of `threads` (torch's
        pool); False where the CPU has no such mode."""
        return bool(self.lib.macb_flush_denormals(int(on), threads))

    @staticmethod
    def _check(*lists: Sequence[torch.Tensor]) -> None:
        sizes = [t.numel() for t in lists[0]]
        for tensors in lists:
            if [t.numel() for t in tensors] != sizes or not all(
                t.is_contiguous() and t.device.type == "cpu" for t in tensors
            ):
                raise ValueError("the fused kernel needs contiguous CPU tensors of equal sizes")

    def adam(
        self,
        params: Sequence[torch.Tensor],
        grads: Sequence[torch.Tensor],
        exp_avgs: Sequence[torch.Tensor],
        exp_avg_sqs: Sequence[torch.Tensor],
        lows: Sequence[torch.Tensor],
        step: float,
        lr: float,
        beta1: float,
        beta2: float,
        eps: float,
    ) -> None:
        """One Adam step (torch's fused kernel's arithmetic) at step number `step` (already
        counted), then every weight's bf16 copy into `lows`."""
        self._check(params, grads, exp_avgs, exp_avg_sqs, lows)
        if any(t.dtype != torch.float32 for t in (*params, *exp_avgs, *exp_avg_sqs)) or any(
            g.dtype not in (torch.float32, torch.bfloat16) for g in grads
        ):
            raise ValueError("Adam's weights and moments must be fp32, gradients fp32 or bf16")
        if any(t.dtype != torch.bfloat16 for t in lows):
            raise ValueError("the copies must be bf16")
        n = len(params)
        self.lib.macb_adam(
            n,
            _array(params),
            _array(grads),
            (ctypes.c_int32 * n)(*[g.dtype == torch.bfloat16 for g in grads]),
            _array(exp_avgs),
            _array(exp_avg_sqs),
            _array(lows),
            (ctypes.c_int64 * n)(*[t.numel() for t in params]),
            *_adam_scalars(step, lr, beta1, beta2, eps),
            self.vec or 1,
            torch.get_num_threads(),
        )

    def adam_soft(
        self,
        params: Sequence[torch.Tensor],
        grads: Sequence[torch.Tensor],
        exp_avgs: Sequence[torch.Tensor],
        exp_avg_sqs: Sequence[torch.Tensor],
        targets: Sequence[torch.Tensor],
        step: float,
        lr: float,
        beta1: float,
        beta2: float,
        eps: float,
        tau: float,
    ) -> None:
        """One Adam step of fp32 weights (as `adam`, without copies), then each weight's
        target soft-updated from it (`soft_update`'s lerp, tau < 0.5), in one pass."""
        if not 0 <= tau < 0.5:
            raise ValueError(f"the fused soft update needs 0 <= tau < 0.5, got {tau}")
        self._check(params, grads, exp_avgs, exp_avg_sqs, targets)
        if any(t.dtype != torch.float32 for t in (*params, *grads, *exp_avgs, *exp_avg_sqs)):
            raise ValueError("adam_soft's weights, gradients and moments must be fp32")
        if any(t.dtype != torch.float32 for t in targets):
            raise ValueError("adam_soft's targets must be fp32")
        n = len(params)
        self.lib.macb_adam_soft(
            n,
            _array(params),
            _array(grads),
            _array(exp_avgs),
            _array(exp_avg_sqs),
            _array(targets),
            (ctypes.c_int64 * n)(*[t.numel() for t in params]),
            *_adam_scalars(step, lr, beta1, beta2, eps),
            self.vec or 1,
            tau,
            torch.get_num_threads(),
        )

    def soft_update(
        self,
        targets: Sequence[torch.Tensor],
        params: Sequence[torch.Tensor],
        lows: Sequence[torch.Tensor],
        tau: float,
    ) -> None:
        """targets <- lerp(targets, params, tau) (tau < 0.5), then their bf16 copies."""
        if not 0 <= tau < 0.5:
            raise ValueError(f"the fused soft update needs 0 <= tau < 0.5, got {tau}")
        self._check(targets, params, lows)
        n = len(targets)
        self.lib.macb_soft_update(
            n,
            _array(targets),
            _array(params),
            _array(lows),
            (ctypes.c_int64 * n)(*[t.numel() for t in targets]),
            tau,
            torch.get_num_threads(),
        )
