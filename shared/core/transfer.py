"""Host arrays onto a device in one copy: what the learner's inputs (`stage`) and a
device replay's rows, indices and bonuses (`GroupReplay`, the trainer's gather) use."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

TORCH_DTYPES = {np.dtype(np.float32): torch.float32, np.dtype(np.int64): torch.int64}

#: Bytes each array starts at a multiple of in `send`'s one buffer (the alignment of a
#: tensor of its own on an accelerator).
SEND_ALIGN = 256


def send(arrays: Sequence[np.ndarray], device: torch.device) -> list[torch.Tensor]:
    """Host arrays of any dtypes (indices, rows, bonuses) as tensors on `device`, in one
    non-blocking copy: written into one byte buffer (pinned on CUDA, kept by the
    caching host allocator until the copy is done), sent at once and viewed back by
    dtype and shape. One transfer per call, and nothing waits for it but the device's
    queue. On the CPU the buffer itself (a fresh one: the caller's arrays stay theirs)."""
    starts, end = [], 0
    for a in arrays:
        starts.append(end)
        end += -(-a.nbytes // SEND_ALIGN) * SEND_ALIGN
    buf = torch.empty(max(end, 1), dtype=torch.uint8, pin_memory=device.type == "cuda")
    flat = buf.numpy()
    for a, at in zip(arrays, starts):
        flat[at : at + a.nbytes].view(a.dtype).reshape(a.shape)[...] = a
    sent = buf.to(device, non_blocking=True)
    return [
        sent[at : at + a.nbytes].view(TORCH_DTYPES[a.dtype]).view(a.shape)
        for a, at in zip(arrays, starts)
    ]
