"""Past one machine: rollouts, evaluation and sweeps on a Ray cluster (``--ray-address``).

Ray is an optional extra (``pip install "idas-sumo[ray]"``). Nothing here imports it at module level:
``require_ray`` does, when a command asks for a cluster, so a run without ``--ray-address`` never
loads it.
"""

from __future__ import annotations

from types import ModuleType

from idas_sumo.errors import InputError

__all__ = ["LOCAL", "RAY_EXTRA", "check_ray_address", "require_ray"]

RAY_EXTRA = 'pip install "idas-sumo[ray]"'
"""How to install what ``--ray-address`` needs (the extra in pyproject.toml pins Ray's version)."""
LOCAL = "local"
"""``--ray-address local``: a Ray instance started by the command itself, on this machine only."""
AUTO = "auto"
"""``--ray-address auto``: the cluster that ``ray start`` started on this machine (or RAY_ADDRESS)."""


def require_ray() -> ModuleType:
    """The ``ray`` module; an ``InputError`` naming the extra when it is not installed."""
    try:
        import ray
    except ImportError:
        raise InputError(f"--ray-address needs Ray, which is not installed: {RAY_EXTRA}") from None
    return ray


def check_ray_address(text: str) -> str:
    """``auto``, ``local`` or ``HOST:PORT`` (a head node's GCS address, as ``ray start --head`` prints
    it); anything else is an ``InputError``."""
    if text in (AUTO, LOCAL):
        return text
    host, sep, port = text.rpartition(":")
    if sep and host.strip() and port.isdigit() and 0 < int(port) < 65536:
        return text
    raise InputError(f"--ray-address: expected auto, local or HOST:PORT, got {text!r}")
