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


CACHED_MODULE = """\
import numpy as np
from idas_sumo.env.jit import kernel, load_cached_kernels


@kernel
def twice(values):
    return values * 2.0
"""


def test_load_cached_kernels_loads_what_an_earlier_process_cached(tmp_path, monkeypatch) -> None:
    """A process that loads the cached kernels needs no load (nor compile) on their first call: a fresh
    process calls a new kernel (compiled and cached); the next one loads it before calling it."""
    import subprocess
    import sys

    (tmp_path / "cached_kernel.py").write_text(CACHED_MODULE)
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba_cache"))

    def run(code: str) -> str:
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
        return done.stdout.strip()

    first = (
        "import numpy as np, cached_kernel as m; print(m.load_cached_kernels(), m.twice(np.ones(2)).sum())"
    )
    assert run(first) == "0 4.0"  # nothing cached yet: compiled on the call
    then = (
        "import numpy as np, cached_kernel as m; n = m.load_cached_kernels(); loaded = len(m.twice.overloads); "
        "m.twice(np.ones(3)); print(n, loaded, len(m.twice.overloads), m.twice._cache_hits.total(), m.twice._cache_misses.total())"
    )
    # Loaded before the call (the one cache hit), which used it: no other overload, no miss.
    assert run(then) == "1 1 1 1 0"
