"""The C heap of a training process, set so that an update's temporaries reuse memory.

Every update allocates and frees the same large temporaries (activations, gradients:
hundreds of kB to a few MB each). glibc's malloc serves blocks above a threshold it
moves at run time with fresh mmap'd pages, and returns free memory at the top of its
heap to the kernel past another: whenever the rest of a step (pricing, sampling,
evaluation, cuts) reshapes the heap, the next update's temporaries come back as new
pages, each a page fault and a page the kernel zeroes. Fixed thresholds above those
sizes keep the pages in the process: the update then reuses the same memory every
step. Where blocks land changes no arithmetic: torch aligns every tensor itself, and
the numbers are the same bit for bit (tests/test_group_trainer.py, tests/test_resume.py).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import platform

log = logging.getLogger("macb.heap")

# "0", "off", "false" or "no" leave glibc's thresholds (read here, not through
# shared.settings, which this layer does not import; documented there).
ENV_SWITCH = "MACB_STEADY_HEAP"

# mallopt's parameters (malloc.h).
M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3

# The largest mmap threshold glibc takes on 64-bit (DEFAULT_MMAP_THRESHOLD_MAX): blocks
# above it (replay buffers, count snapshots) are still mapped and returned at once.
MMAP_THRESHOLD = 32 << 20
# Free memory kept at the top of the heap before any is returned to the kernel.
TRIM_THRESHOLD = 512 << 20
# Extra memory asked of the kernel with every heap extension.
TOP_PAD = 16 << 20

_done = False


def steady_heap() -> bool:
    """Set this process's malloc thresholds as the module docstring says (once; glibc
    only, elsewhere nothing; MACB_STEADY_HEAP=0 leaves them). Returns whether they are set."""
    global _done
    if _done:
        return True
    if os.environ.get(ENV_SWITCH, "").strip().lower() in ("0", "off", "false", "no"):
        return False
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    ok = all(
        mallopt(param, value) == 1
        for param, value in (
            (M_MMAP_THRESHOLD, MMAP_THRESHOLD),
            (M_TRIM_THRESHOLD, TRIM_THRESHOLD),
            (M_TOP_PAD, TOP_PAD),
        )
    )
    if not ok:
        log.warning("mallopt refused a heap setting: the update's temporaries may fault")
    _done = ok
    return ok
