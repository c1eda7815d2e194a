"""The engine's kernels compile wherever the package is installed, with or without a disk cache."""

from __future__ import annotations

import numpy as np
import pytest

from idas_sumo.env.jit import kernel


def _add_one(values):
    out = np.empty_like(values)
    for i in range(values.shape[0]):
        out[i] = values[i] + 1.0
    return out


def test_a_kernel_compiles_and_caches_where_numba_can_write() -> None:
    compiled = kernel(_add_one)
    assert compiled(np.array([1.0, 2.5])).tolist() == [2.0, 3.5]
    assert compiled._cache is not None and compiled._cache._impl.locator is not None  # type: ignore[attr-defined]


def test_without_anywhere_to_cache_a_kernel_still_compiles(monkeypatch: pytest.MonkeyPatch) -> None:
    """A read-only install with no writable home: numba's cache=True raises as the module is imported;
    the kernel is compiled per process instead."""
    import numba.core.caching as caching

    monkeypatch.setattr(caching.CacheImpl, "_locator_classes", [])
    with pytest.raises(RuntimeError, match="no locator available"):
        import numba

        numba.njit(cache=True)(_add_one)
    compiled = kernel(_add_one)
    assert compiled(np.array([-1.0])).tolist() == [0.0]
