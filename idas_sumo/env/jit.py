"""The engine's compiled loops: ``numba.njit``, with the machine code cached on disk where numba can write.

numba compiles a kernel on its first call (about 2 s for all of the engine's) and, with ``cache=True``, keeps
the machine code beside the source or in the user's cache directory, whichever it can write first, so later
processes only load it. Where it can write neither (a read-only install and no writable home), ``cache=True``
fails as the module is imported; ``kernel`` then compiles without a disk cache, once per process.

numba tells a stale cache by the kernel's own source file only. A kernel that calls a kernel of another module
(the masks call ``physics/idm.py``'s ``idm_acceleration_one``; the grids call ``snapshot.same_lane``; the
engine's own-lane masks, in ``front_cars.py``, call ``snapshot.py``'s leader walk, ``actions.py``'s mask
kernel and ``observation.py``'s observation kernel; the engine's read, in ``routes.py``, calls ``snapshot.py``'s sort and ``collisions.py``'s overlap scan;
``kernels.py``'s ``_allowed_step`` calls ``actions.py``'s ``_candidate``; ``agents/run_blocks.py``'s kernels call ``agents/run_conv.py``'s ``add_piece`` and ``four_rows``) keeps the old machine code when only that other module changes: after editing such a callee, delete the ``*.nbi`` and
``*.nbc`` files under ``idas_sumo/`` (a fresh checkout or install has none).

Two habits keep a kernel's inner loop vectorised (numba gives LLVM no proof that two arrays do not overlap): loop
over slices (``dst = out[a:b]; for k in range(b - a): dst[k] += ...``) rather than with an offset inside the
index, and where a loop adds into an array once per term, add several terms a pass in their order
(``out[j] = ((out[j] + t0[j]) + t1[j]) + ...``: the same floats, the array read and written a fraction as often).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar, cast

import numba
import numpy as np
import numpy.typing as npt

F = TypeVar("F", bound=Callable[..., Any])

_KERNELS: list[Any] = []
"""Every kernel made by ``kernel`` (numba dispatchers), for ``load_cached_kernels``."""


def kernel(func: F) -> F:
    """``func`` compiled by numba (nopython, releasing the GIL), cached on disk where possible."""
    try:
        compiled = numba.njit(cache=True, nogil=True)(func)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        compiled = numba.njit(nogil=True)(func)
    _KERNELS.append(compiled)
    return cast(F, compiled)


def load_cached_kernels() -> int:
    """Load now the machine code numba cached for every kernel imported so far (each signature it holds for
    this machine and this source), as each kernel's first call would: a process that forks workers calls
    this once, so that none of them loads the same code again. Returns how many were loaded; a kernel whose
    cache cannot be read (none yet, stale, another numba) is left to compile or load on its first call."""
    loaded = 0
    for dispatcher in _KERNELS:
        cache = dispatcher._cache  # (numba's own cache of the kernel: its index lists the cached signatures)
        try:
            codegen = dispatcher.targetctx.codegen()
            for sig, machine, source in cache._cache_file._load_index():
                if (sig, machine, source) == cache._index_key(sig, codegen):
                    dispatcher.compile(sig)
                    loaded += 1
        except Exception:  # (a speed-up only: the kernel's first call does it otherwise)
            continue
    return loaded


def per_row(values: npt.ArrayLike | None, n: int, dtype: type = np.float64) -> npt.NDArray[Any]:
    """``values`` (None: zeros) as n contiguous rows of ``dtype``: a kernel reads row i of each input
    unchecked, so a scalar or a shorter input is broadcast first (an input that is already right passes)."""
    if isinstance(values, np.ndarray) and values.shape == (n,) and values.dtype == dtype:
        return np.ascontiguousarray(values)
    return np.ascontiguousarray(
        np.broadcast_to(np.asarray(0 if values is None else values, dtype=dtype), (n,))
    )
