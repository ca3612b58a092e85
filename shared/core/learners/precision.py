"""Which precision the batched learner's matrix products run in, and whether the CPU can.

`bf16` pays where the CPU has bfloat16 dot-product instructions (AVX512-BF16 or AMX-BF16),
which torch's oneDNN matmul kernels use; elsewhere bf16 is emulated around fp32
arithmetic and not known to pay for the precision it loses, so a learner asked for bf16
on such a CPU runs fp32 and says so once, in its log and in its stats. The detection reads
the CPU flags the kernel reports (docs/performance.md, "bf16", has what torch does on
this project's CPU).
"""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import torch

PRECISIONS = ("fp32", "bf16")
# CPU flags (as in /proc/cpuinfo) of native bf16 dot products.
NATIVE_BF16_FLAGS = ("avx512_bf16", "amx_bf16")
DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16}

log = logging.getLogger("macb.learners")


def cpu_flags(cpuinfo: str) -> set[str]:
    """The flags of every processor listed in a /proc/cpuinfo text."""
    flags: set[str] = set()
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "flags":
            flags.update(value.split())
    return flags


@functools.cache
def native_bf16() -> bool:
    """Whether this CPU has native bf16 dot products (False where /proc/cpuinfo is absent,
    e.g. not Linux: there bf16 is not known to pay, so fp32 is kept)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return any(flag in cpu_flags(text) for flag in NATIVE_BF16_FLAGS)


def resolve(precision: str, device: torch.device | None = None) -> str:
    """The precision a learner asked for `precision` runs in: bf16 only where the CPU has
    native bf16 (`native_bf16`), otherwise fp32, with one warning. On an accelerator
    bf16 is the device's to run."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if device is not None and device.type != "cpu":
        return precision
    if precision == "bf16" and not native_bf16():
        log.warning(
            "precision bf16 asked for, but this CPU has no native bf16 (no %s in its flags): "
            "the learner runs fp32",
            " or ".join(NATIVE_BF16_FLAGS),
        )
        return "fp32"
    return precision


class DeviceError(ValueError):
    """A device this torch build or machine cannot run the learner on."""


def resolve_device(device: str | torch.device) -> torch.device:
    """The learner's torch device, refused with the reason when it cannot be used here.
    `meta` (tensors with shapes and no data, so any read of a value fails) is taken for
    the tests that show an update and `act` never read the device from the host."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise DeviceError(f"device {device!r}: not a torch device ({err})") from None
    if dev.type in ("cpu", "meta"):
        return dev
    module = getattr(torch, dev.type, None)
    available = getattr(module, "is_available", None)
    if available is None or not available():
        raise DeviceError(
            f"device {device}: not available here (torch {torch.__version__} on this machine "
            f"has no usable {dev.type}); use device cpu"
        )
    count = getattr(module, "device_count", lambda: 1)()
    if dev.index is not None and dev.index >= count:
        raise DeviceError(f"device {device}: this machine has {count} {dev.type} device(s)")
    return dev


def device_count(device: str) -> int:
    """How many devices a config's `device` can spread groups over: every GPU of its
    kind for a bare `cuda` or `xpu` (0 where there is none), one for a numbered one or
    `mps`, 0 for the CPU."""
    dev = torch.device(device)
    if dev.type == "cpu":
        return 0
    if dev.index is not None:
        return 1
    module = getattr(torch, dev.type, None)
    available = getattr(module, "is_available", None)
    if available is None or not available():
        return 0
    return int(getattr(module, "device_count", lambda: 1)())
