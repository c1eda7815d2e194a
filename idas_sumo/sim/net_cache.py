"""Generated merge nets by their parameters, built once and kept in a cache.

Training that draws a fresh geometry per episode or per round asks ``cached_net(params)`` for the net
file: the first call runs netconvert (a fraction of a second), later calls with the same parameters
return the same file. The key is a hash of every ``NetParams`` field, the netconvert version (a new
SUMO may build a different net from the same plain XML) and ``CACHE_FORMAT``. Nets live in a ``gen``
folder of the multi-copy net cache (``IDAS_SUMO_CACHE``, see sim/multinet.py).

Concurrent workers asking for one key are safe: each builds in a private temp folder inside the cache
and renames the finished net into place (``generate_net`` writes atomically), so a reader never sees a
half-written file and the last rename wins with identical content. A net is read back and checked
(``read_merge_net``) before it is renamed into the cache.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

from idas_sumo.errors import SimulationError
from idas_sumo.io_utils import remove_stale_temps
from idas_sumo.sim.multinet import STALE_TEMP_S, default_cache_dir
from idas_sumo.sim.netgen import NetParams, generate_net, read_merge_net, sumo_binary

CACHE_FORMAT = 1
"""Bump when ``generate_net`` changes the nets it writes: older cached nets are then not reused."""
GEN_SUBDIR = "gen"
"""The generated nets' folder inside the net cache."""
BUILD_DIR_PREFIX = ".build-"
"""A private build folder inside the cache (removed after the build; a killed build's is stale)."""


@functools.cache
def netconvert_version() -> str:
    """The first line of ``netconvert --version`` (e.g. ``Eclipse SUMO netconvert 1.28.0``)."""
    binary = sumo_binary("netconvert")
    result = subprocess.run([str(binary), "--version"], capture_output=True, text=True, check=False)
    lines = result.stdout.strip().splitlines()
    if result.returncode != 0 or not lines:
        raise SimulationError(f"{binary} --version failed: {result.stderr.strip().splitlines()[-1:]}")
    return lines[0].strip()


def params_key(params: NetParams) -> str:
    """Hex digest naming the net of ``params`` (every field, the netconvert version, the cache format)."""
    fields = json.dumps(dataclasses.asdict(params), sort_keys=True)
    text = f"{fields}\0netconvert={netconvert_version()}\0format={CACHE_FORMAT}"
    return hashlib.sha256(text.encode()).hexdigest()


def cached_net(params: NetParams, cache_dir: str | Path | None = None) -> Path:
    """The generated merge net for ``params``: from the cache, or built, checked and cached now."""
    folder = (Path(cache_dir) if cache_dir is not None else default_cache_dir()) / GEN_SUBDIR
    path = folder / f"merge-{params_key(params)[:32]}.net.xml"
    if path.is_file():
        return path
    folder.mkdir(parents=True, exist_ok=True)
    _remove_stale_builds(folder)
    build = Path(tempfile.mkdtemp(dir=folder, prefix=BUILD_DIR_PREFIX))
    try:
        built = generate_net(build / path.name, params)
        read_merge_net(built)  # a net that does not read back as a merge never enters the cache
        os.replace(built, path)
    finally:
        shutil.rmtree(build, ignore_errors=True)
    return path


def _remove_stale_builds(folder: Path) -> None:
    remove_stale_temps(folder, older_than_s=STALE_TEMP_S)
    now = time.time()
    for build in folder.glob(f"{BUILD_DIR_PREFIX}*"):
        try:
            if now - build.stat().st_mtime > STALE_TEMP_S:
                shutil.rmtree(build, ignore_errors=True)
        except OSError:  # another worker removed it first
            continue


__all__ = ["CACHE_FORMAT", "cached_net", "netconvert_version", "params_key"]
