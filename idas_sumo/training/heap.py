"""glibc's allocator, told to keep a training process's large freed blocks for reuse.

A training round allocates and frees arrays of tens of MB again and again: the round's observations, the
learner's conv outputs and their gradients. glibc serves a block that large from fresh pages of the kernel
(``mmap``) and hands them back when it is freed, so every round page-faults and zeroes them anew: about
8,000 faults in one worker's gradient of 8 episodes. With the thresholds raised, such blocks come from the
heap and stay there: the median CPU time of a round's collection and gradient fell by about 15 %
(``docs/performance.md``).
Which memory an array gets changes no value computed in it. Linux with glibc only; elsewhere nothing
changes.

And Python's cyclic garbage collector, told to leave alone the objects a training process holds for the whole
run (``frozen_heap``): its full collections otherwise walk every one of them, the imported torch, numba and
their caches included, about 0.1 s each.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import gc
import sys
from collections.abc import Iterator

M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3
"""``mallopt`` parameters (glibc's ``malloc.h``)."""

KEEP_BELOW_BYTES = 1 << 30
"""Blocks under this size come from the heap, and the heap keeps this much free memory before it trims."""
TOP_PAD_BYTES = 64 << 20
"""How much more the heap grows by than a request needs."""


def keep_freed_blocks() -> bool:
    """Raise glibc's mmap and trim thresholds for this process; whether it took effect (False: not glibc)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl and other C libraries have no mallopt
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    settings = (
        (M_MMAP_THRESHOLD, KEEP_BELOW_BYTES),
        (M_TRIM_THRESHOLD, KEEP_BELOW_BYTES),
        (M_TOP_PAD, TOP_PAD_BYTES),
    )
    return all(mallopt(param, value) == 1 for param, value in settings)


def freeze_alive() -> None:
    """Put the objects alive now out of the cyclic garbage collector's reach (``gc.freeze``), after a collection of
    the young generations' garbage (a frozen cycle is not freed until it is unfrozen). The old generation is not
    collected: after the imports it held a few dozen garbage objects, and its walk costs 0.1-0.2 s of a run's
    start while the workers wait. Which collections run never changes a value."""
    gc.collect(1)
    gc.freeze()


@contextlib.contextmanager
def frozen_heap() -> Iterator[None]:
    """Within the block, the objects alive at its start are frozen (``freeze_alive``); at its end they are back in
    the collector's reach."""
    freeze_alive()
    try:
        yield
    finally:
        gc.unfreeze()
