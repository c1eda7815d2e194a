"""``evaluate --suite geometry``: the paper protocol on merges the training never saw.

Each geometry is evaluated as ``--suite paper`` on its own net (the same scenarios per method, the
scenario draws scaled to that net's limits and lengths), into ``OUT/<geometry>/``; ``OUT/geometry.csv``
holds every geometry's summary rows with the geometry's name first. The held-out geometries are
generated T-junctions (``sim/net_cache.cached_net``: built once, then read from the cache) whose angle,
lengths, limits or priority differ from the shipped net's (angle 30°, roads 250/250/150 m, limits
20/15/20 m/s, the main road first), and the ``onramp`` sample net (a two-lane highway with an
acceleration lane, built from plain XML each run).
"""

from __future__ import annotations

import dataclasses
import tempfile
from collections.abc import Callable
from pathlib import Path

import pandas as pd

from idas_sumo.evaluation.runner import EvalOutput, EvalRequest, run_evaluation
from idas_sumo.io_utils import atomic_open
from idas_sumo.sim.merge_detect import MergeSite
from idas_sumo.sim.net_cache import cached_net
from idas_sumo.sim.netgen import NetParams
from idas_sumo.sim.sample_nets import build_sample_net

HELD_OUT_GEOMETRIES: tuple[tuple[str, NetParams], ...] = (
    ("angle-15", NetParams(angle_deg=15.0)),
    ("angle-60", NetParams(angle_deg=60.0)),
    ("roads-220", NetParams(main_length_m=220.0, merge_length_m=220.0)),
    ("roads-350", NetParams(main_length_m=350.0, merge_length_m=350.0)),
    ("limits-25-18", NetParams(main_speed_mps=25.0, merge_speed_mps=18.0, out_speed_mps=25.0)),
    ("zipper", NetParams(priority="equal", merge_speed_mps=20.0)),
)
"""Generated merges unlike the shipped one in one respect each. Roads shorter than 205 m cannot hold
the paper suite's starts (200 m and a car)."""
SAMPLE_GEOMETRIES: tuple[str, ...] = ("onramp",)
"""Sample nets (``sim/sample_nets.py``) evaluated as they are: merges of another kind."""
GEOMETRY_CSV = "geometry.csv"


def geometry_nets(workdir: Path, cache_dir: str | Path | None = None) -> list[tuple[str, Path]]:
    """(name, net file) of every geometry of the suite; sample nets are built into ``workdir``."""
    nets = [(name, cached_net(params, cache_dir)) for name, params in HELD_OUT_GEOMETRIES]
    nets += [(name, build_sample_net(name, workdir / f"{name}.net.xml")) for name in SAMPLE_GEOMETRIES]
    return nets


def run_geometry_suite(
    request: EvalRequest,
    check_net: Callable[[Path], MergeSite],
    on_geometry: Callable[[str, EvalOutput], None] | None = None,
    cache_dir: str | Path | None = None,
) -> tuple[list[tuple[str, EvalOutput]], Path]:
    """``request`` (its ``net`` and ``suite`` replaced) run on every geometry into ``request.out /
    name``; ``check_net`` refuses a net the scenarios cannot use (the CLI's road checks) before it
    runs, and gives its merge site; ``on_geometry`` sees each result as it comes. The results and the combined CSV's path."""
    results: list[tuple[str, EvalOutput]] = []
    with tempfile.TemporaryDirectory(prefix="idas_sumo_geometry_") as tmp:
        for name, net in geometry_nets(Path(tmp), cache_dir):
            site = check_net(net)
            env = dataclasses.replace(request.env, junction=None) if request.env is not None else None
            output = run_evaluation(
                dataclasses.replace(
                    request,
                    net=net,
                    site=site,
                    env=env,
                    suite="paper",
                    out=request.out / name,
                    fresh_out=False,
                )
            )
            results.append((name, output))
            if on_geometry is not None:
                on_geometry(name, output)
    table = pd.concat([out.summary.assign(geometry=name) for name, out in results], ignore_index=True)
    table = table[["geometry", *(c for c in table.columns if c != "geometry")]]
    path = request.out / GEOMETRY_CSV
    with atomic_open(path) as f:
        table.to_csv(f, index=False)
    return results, path


__all__ = ["GEOMETRY_CSV", "HELD_OUT_GEOMETRIES", "SAMPLE_GEOMETRIES", "geometry_nets", "run_geometry_suite"]
