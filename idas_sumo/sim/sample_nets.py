"""Small SUMO networks built with netconvert from plain XML, for tests and for trying nets users bring.

- ``onramp``: a curved two-lane highway (33 m/s) with a single-lane on-ramp (22 m/s) that joins it as
  an acceleration lane (the highway's rightmost lane on the ``accel`` edge), which ends 200 m on
  (a lane drop: netconvert gives the ending lane no connection, cars must change lanes). The kind of
  merge an OSM import of a motorway junction gives.
- ``two_merges``: a single-lane road with two single-lane side roads joining it one after the other
  (two edge-level merges, junctions ``j1`` and ``j2``).
- ``crossing``: a four-way crossing of two-way roads (every incoming road leads to three outgoing
  ones: not a merge).
- ``straight``: one road made of two edges (no junction with two incoming roads).

Nothing is downloaded; ``build_sample_net(name, out)`` writes ``out`` atomically and keeps the plain
XML beside it; ``build_plain_net`` builds any net from plain XML the same way.
"""

from __future__ import annotations

import subprocess
from collections.abc import Callable
from pathlib import Path

from idas_sumo.errors import InputError, SimulationError
from idas_sumo.io_utils import atomic_path
from idas_sumo.sim.netgen import sumo_binary, write_plain_xml

HIGHWAY_SPEED_MPS = 33.0
"""The on-ramp net's highway limit (about 120 km/h)."""
RAMP_SPEED_MPS = 22.0
"""The on-ramp net's ramp limit (about 80 km/h)."""
SIDE_ROAD_SPEED_MPS = 15.0
"""The two-merge, crossing and straight nets' limit."""

_Plain = tuple[str, str, str]
"""Plain XML of a net: nodes, edges, connections ("" for netconvert's own)."""


def _onramp() -> _Plain:
    nodes = """<nodes>
  <node id="hw_start" x="-650" y="60"/>
  <node id="ramp_start" x="-420" y="-150"/>
  <node id="gore" x="0" y="0"/>
  <node id="drop" x="200" y="0"/>
  <node id="hw_end" x="600" y="50"/>
</nodes>
"""
    hw, ramp = HIGHWAY_SPEED_MPS, RAMP_SPEED_MPS
    edges = f"""<edges>
  <edge id="hw_in" from="hw_start" to="gore" numLanes="2" speed="{hw}" priority="3"
        shape="-650,60 -450,55 -250,30 -100,5 0,0"/>
  <edge id="ramp" from="ramp_start" to="gore" numLanes="1" speed="{ramp}" priority="1"
        shape="-420,-150 -330,-100 -220,-50 -100,-12 0,-3"/>
  <edge id="accel" from="gore" to="drop" numLanes="3" speed="{hw}" priority="3"/>
  <edge id="hw_out" from="drop" to="hw_end" numLanes="2" speed="{hw}" priority="3"
        shape="200,0 350,5 480,20 600,50"/>
</edges>
"""
    # The ramp's lane becomes the acceleration lane (accel_0); the highway's lanes go on beside it.
    connections = """<connections>
  <connection from="ramp" to="accel" fromLane="0" toLane="0"/>
  <connection from="hw_in" to="accel" fromLane="0" toLane="1"/>
  <connection from="hw_in" to="accel" fromLane="1" toLane="2"/>
</connections>
"""
    return nodes, edges, connections


def _two_merges() -> _Plain:
    nodes = """<nodes>
  <node id="a" x="-400" y="0"/>
  <node id="r1" x="-300" y="-150"/>
  <node id="j1" x="0" y="0"/>
  <node id="r2" x="200" y="-150"/>
  <node id="j2" x="400" y="0"/>
  <node id="end" x="700" y="0"/>
</nodes>
"""
    v = SIDE_ROAD_SPEED_MPS
    edges = f"""<edges>
  <edge id="a_j1" from="a" to="j1" numLanes="1" speed="{v}" priority="2"/>
  <edge id="r1_j1" from="r1" to="j1" numLanes="1" speed="{v}" priority="1"/>
  <edge id="j1_j2" from="j1" to="j2" numLanes="1" speed="{v}" priority="2"/>
  <edge id="r2_j2" from="r2" to="j2" numLanes="1" speed="{v}" priority="1"/>
  <edge id="j2_end" from="j2" to="end" numLanes="1" speed="{v}" priority="2"/>
</edges>
"""
    return nodes, edges, ""


def _crossing() -> _Plain:
    arms = {"w": (-200, 0), "e": (200, 0), "s": (0, -200), "n": (0, 200)}
    nodes = (
        "<nodes>\n"
        + '  <node id="c" x="0" y="0" type="priority"/>\n'
        + "".join(f'  <node id="{k}" x="{x}" y="{y}"/>\n' for k, (x, y) in arms.items())
        + "</nodes>\n"
    )
    v = SIDE_ROAD_SPEED_MPS
    edges = (
        "<edges>\n"
        + "".join(
            f'  <edge id="{k}_in" from="{k}" to="c" numLanes="1" speed="{v}"/>\n'
            f'  <edge id="{k}_out" from="c" to="{k}" numLanes="1" speed="{v}"/>\n'
            for k in arms
        )
        + "</edges>\n"
    )
    return nodes, edges, ""


def _straight() -> _Plain:
    nodes = '<nodes>\n  <node id="a" x="0" y="0"/>\n  <node id="b" x="200" y="0"/>\n  <node id="c" x="400" y="0"/>\n</nodes>\n'
    v = SIDE_ROAD_SPEED_MPS
    edges = (
        "<edges>\n"
        f'  <edge id="ab" from="a" to="b" numLanes="1" speed="{v}"/>\n'
        f'  <edge id="bc" from="b" to="c" numLanes="1" speed="{v}"/>\n'
        "</edges>\n"
    )
    return nodes, edges, ""


SAMPLE_NETS: dict[str, Callable[[], _Plain]] = {
    "onramp": _onramp,
    "two_merges": _two_merges,
    "crossing": _crossing,
    "straight": _straight,
}
"""Name -> the net's plain XML."""


def build_sample_net(name: str, out: str | Path, force: bool = False) -> Path:
    """Build the sample net ``name`` into ``out`` (a .net.xml) with netconvert; its plain XML is kept
    beside it. A file the tool did not write is replaced only with ``force``."""
    if name not in SAMPLE_NETS:
        raise InputError(f"sample net {name!r}: not one of {', '.join(SAMPLE_NETS)}")
    return build_plain_net(*SAMPLE_NETS[name](), out, force=force)


def _plain_kinds(nodes_xml: str, edges_xml: str, connections_xml: str) -> list[tuple[str, str, str]]:
    """(netconvert flag, file kind, text) of each plain XML file."""
    return [("-n", "nod", nodes_xml), ("-e", "edg", edges_xml), ("-x", "con", connections_xml)]


def build_plain_net(
    nodes_xml: str, edges_xml: str, connections_xml: str, out: str | Path, force: bool = False
) -> Path:
    """A net from plain XML (nodes, edges, connections: "" for netconvert's own) into ``out``,
    written atomically, the plain XML kept beside it (``<stem>.nod.xml`` ...)."""
    path = Path(out)
    given = [
        (flag, kind, text) for flag, kind, text in _plain_kinds(nodes_xml, edges_xml, connections_xml) if text
    ]
    files = write_plain_xml(path, [(kind, text) for _, kind, text in given], force)
    cmd = [str(sumo_binary("netconvert"))]
    for (flag, _, _), plain in zip(given, files, strict=True):
        cmd += [flag, str(plain)]
    with atomic_path(path) as tmp:
        cmd += ["-o", str(tmp), "--no-turnarounds", "true", "--no-warnings", "true"]
        result = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if result.returncode != 0:
            raise SimulationError(f"netconvert failed on {path}: {result.stderr.strip()[-300:]}")
    return path


__all__ = ["HIGHWAY_SPEED_MPS", "RAMP_SPEED_MPS", "SAMPLE_NETS", "build_plain_net", "build_sample_net"]
