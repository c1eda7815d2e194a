"""Generated merge nets by their parameters, built once and kept in a cache.

Training that draws a fresh geometry per episode or per round asks ``cached_net(params)`` for the net
file: the first call runs netconvert (a fraction of a second), later calls with the same parameters
return the same file. The key is a hash of every ``NetParams`` field, the netconvert version (a new
SUMO may build a different net from the same plain XML) and ``CACHE_FORMAT``. Nets live in a ``gen``
folder of the multi-copy net cache (``IDAS_SUMO_CACHE``, see sim/multinet.py).

Concurrent workers asking for one key are safe: each builds in a private temp folder inside the cache
and renames the finished net, then its digest, into place, so a reader never sees a half-written file.
A net is read back and checked (``read_merge_net``) before it enters the cache, and a cached net is
used only if it still has the SHA-256 written beside it when it was built (netconvert stamps the build
time into the file, so two racing builds can leave one's net beside the other's digest: the next call
then builds it again) and, checked once per process, still reads as a merge and loads in a SUMO child
process (``multinet.cached_file_ok``).
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
from idas_sumo.io_utils import file_digest, remove_stale_temps
from idas_sumo.sim.multinet import STALE_TEMP_S, cached_file_ok, default_cache_dir, remember_checked
from idas_sumo.sim.netgen import NetParams, generate_net, read_merge_net, sumo_binary

CACHE_FORMAT = 1
"""Bump when ``generate_net`` changes the nets it writes: older cached nets are then not reused."""
GEN_SUBDIR = "gen"
"""The generated nets' folder inside the net cache."""
DIGEST_SUFFIX = ".sha256"
"""Beside each cached net: the SHA-256 of the file as built and checked."""
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
    digest = path.with_name(path.name + DIGEST_SUFFIX)
    # Used only with the digest written when it was built and if it still reads as a merge and loads
    # in SUMO: a truncated or edited cache file would otherwise fail later as if the net were bad, run
    # with other roads, or crash SUMO.
    if cached_file_ok(path, digest, read_merge_net):
        return path
    folder.mkdir(parents=True, exist_ok=True)
    _remove_stale_builds(folder)
    build = Path(tempfile.mkdtemp(dir=folder, prefix=BUILD_DIR_PREFIX))
    try:
        built = generate_net(build / path.name, params)
        read_merge_net(built)  # a net that does not read back as a merge never enters the cache
        built_digest = build / digest.name
        built_digest.write_text(file_digest(built) + "\n")
        os.replace(built, path)
        os.replace(built_digest, digest)
    finally:
        shutil.rmtree(build, ignore_errors=True)
    remember_checked(path)
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
