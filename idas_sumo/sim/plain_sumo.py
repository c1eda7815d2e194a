"""A scenario as plain SUMO files: a ``.sumocfg``, a ``.rou.xml`` and a copy of the net, which ``sumo`` and
``sumo-gui`` run without idas-sumo (``idas-sumo export``).

The route file is the engine's own (``backend._route_xml``: the same vTypes, routes, departure times,
positions and speeds), with a comment on top saying what differs: idas-sumo sets the speed of every car of
vType ``agent`` each step from a policy; plain SUMO has no policy, so its car-following model drives those
cars too. The ``.sumocfg`` holds the engine's SUMO options (``backend.run_options``), so the robot cars
drive as they do in an episode.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from pathlib import Path
from xml.sax.saxutils import quoteattr

from idas_sumo.io_utils import atomic_open
from idas_sumo.sim.backend import (
    CONTROLLED_TYPE,
    ROBOT_TYPE,
    STEP_LENGTH_S,
    RouteScenario,
    _route_xml,
    has_lane_changes,
    run_options,
)
from idas_sumo.sim.merge_detect import MergeSite

CONFIG_SUFFIX = ".sumocfg"
ROUTES_SUFFIX = ".rou.xml"
SECTIONS: dict[str, str] = {
    "begin": "time",
    "end": "time",
    "step-length": "time",
    "seed": "random_number",
    "no-step-log": "report",
    "no-warnings": "report",
}
"""The ``.sumocfg`` section of an option (SUMO reads an option in any section; these are the ones its own
``--save-configuration`` uses); any other option goes under ``processing``."""


def plain_files(name: str, net_path: Path) -> tuple[str, str, str]:
    """The names ``write_plain_sumo`` writes for scenario ``name``: config, routes, the net's copy."""
    return f"{name}{CONFIG_SUFFIX}", f"{name}{ROUTES_SUFFIX}", net_path.name


def _comment(lines: Sequence[str]) -> str:
    """An XML comment of ``lines``; ``--`` cannot stand inside one."""
    body = "\n".join(f"     {line}".rstrip() for line in lines).replace("--", "- -")
    return f"<!--\n{body}\n-->"


def driver_note(site: MergeSite) -> list[str]:
    """What the route file's comment says of who drives whom."""
    note = [
        f'SUMO drives every car here. In idas-sumo a policy drives the cars of vType "{CONTROLLED_TYPE}":',
        f"it sets their speed every {STEP_LENGTH_S:g} s step (SUMO's own checks off). Plain SUMO has no",
        "policy, so its car-following model (Krauss) drives them with their vType's limits, as it drives",
        f'the "{ROBOT_TYPE}" cars in idas-sumo too. The departures, positions, speeds and routes are the',
        "scenario's; what happens after the start is SUMO's, not the policy's episode.",
    ]
    if has_lane_changes(site):
        note += [
            "In idas-sumo every car on this multi-lane merge keeps its lane unless its route needs a change",
            "(a lane-change mode set as it departs); here SUMO's default lane changing applies.",
        ]
    return note


def sumocfg_xml(net_name: str, routes_name: str, seed: int, comment: Sequence[str] = ()) -> str:
    """The ``.sumocfg``: the two files (relative: SUMO reads them beside the config) and the engine's options."""
    options = run_options(seed)
    sections: dict[str, list[tuple[str, str]]] = {
        "input": [("net-file", net_name), ("route-files", routes_name)]
    }
    for flag, value in zip(options[::2], options[1::2], strict=True):
        key = flag.removeprefix("--")
        sections.setdefault(SECTIONS.get(key, "processing"), []).append((key, value))
    lines = ['<?xml version="1.0" encoding="UTF-8"?>']
    if comment:
        lines.append(_comment(comment))
    lines.append("<configuration>")
    for section, entries in sections.items():
        lines += [f"    <{section}>", *(f"        <{k} value={quoteattr(v)}/>" for k, v in entries)]
        lines.append(f"    </{section}>")
    lines.append("</configuration>")
    return "\n".join(lines) + "\n"


def write_plain_sumo(
    out: Path,
    name: str,
    scenario: RouteScenario,
    site: MergeSite,
    seed: int,
    notes: Sequence[str] = (),
) -> tuple[Path, Path, Path]:
    """Write ``name.sumocfg``, ``name.rou.xml`` and a copy of ``site``'s net into the folder ``out``, each
    atomically; (config, routes, net). ``notes``: more lines for the route file's comment (where the
    scenario came from, each car's driver type)."""
    config_name, routes_name, net_name = plain_files(name, site.path)
    routes = _route_xml(scenario, site)  # the engine's own route file
    head, rest = routes.split("\n", 1)
    comment = _comment([*driver_note(site), *([""] if notes else []), *notes])
    with atomic_open(out / routes_name) as f:
        f.write(f"{head}\n{comment}\n{rest}")
    with atomic_open(out / net_name, "wb") as f, site.path.open("rb") as net:
        shutil.copyfileobj(net, f)
    run = f"Run it: sumo -c {config_name}   (or sumo-gui -c {config_name})"
    with atomic_open(out / config_name) as f:
        f.write(sumocfg_xml(net_name, routes_name, seed, [f"Exported by idas-sumo. {run}"]))
    return out / config_name, out / routes_name, out / net_name


__all__ = ["driver_note", "plain_files", "sumocfg_xml", "write_plain_sumo"]
