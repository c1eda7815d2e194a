"""Generate the two-road merge network with netconvert, and read a merge network back with sumolib.

Layout: the main road runs straight into the merge junction; the merge road joins it at ``angle_deg``;
one outgoing road leaves the junction. Every edge carries an explicit ``length`` so the roads measure
exactly what was asked to the merge point (netconvert would otherwise trim them at the junction).

Priority: ``main`` gives the main road right of way (a priority junction, main edge priority above the
merge edge's); ``equal`` gives both roads the same edge priority on a zipper junction. Equal edge
priorities alone are not enough: on a priority junction netconvert then ranks the roads by geometry and
the straight main road keeps its right of way (connection states M and m); a zipper junction makes both
connections Z (SUMO's drivers take turns).
"""

from __future__ import annotations

import errno
import math
import os
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from idas_sumo.errors import InputError, SimulationError
from idas_sumo.io_utils import atomic_open, atomic_path, claim_output_file

_BAD_PLACE_ERRNOS = frozenset(
    {errno.ENOENT, errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.EISDIR}
)
"""Errors that mean ``--out`` names a place files cannot be written (bad input, exit 2), unlike a full disk."""

MAIN_EDGE = "main"
MERGE_EDGE = "merge"
OUT_EDGE = "out"
MERGE_JUNCTION = "merge_point"
MAIN_EDGE_PRIORITY = 2  # SUMO road priority: the main road has right of way at the junction
MERGE_EDGE_PRIORITY = 1
PRIORITIES = ("main", "equal")
"""``NetParams.priority``: the main road has right of way, or neither road has (a zipper junction)."""
LENGTH_BOUNDS_M = (20.0, 10_000.0)
SPEED_BOUNDS_MPS = (1.0, 70.0)
ANGLE_BOUNDS_DEG = (5.0, 90.0)


@dataclass(frozen=True)
class NetParams:
    """Geometry and limits of the generated merge (defaults: the paper, outgoing road ours)."""

    main_length_m: float = 250.0
    merge_length_m: float = 250.0
    out_length_m: float = 150.0
    main_speed_mps: float = 20.0
    merge_speed_mps: float = 15.0
    out_speed_mps: float = 20.0
    angle_deg: float = 30.0
    """Angle between the merge road and the main road."""
    priority: str = "main"
    """Who has right of way at the merge: ``main`` (the paper's net) or ``equal`` (a zipper junction)."""

    def __post_init__(self) -> None:
        lo, hi = LENGTH_BOUNDS_M
        for name in ("main_length_m", "merge_length_m", "out_length_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and lo <= value <= hi):
                raise InputError(f"--{_flag(name)}: {value} m is outside [{lo:g}, {hi:g}] m")
        lo, hi = SPEED_BOUNDS_MPS
        for name in ("main_speed_mps", "merge_speed_mps", "out_speed_mps"):
            value = getattr(self, name)
            if not (math.isfinite(value) and lo <= value <= hi):
                raise InputError(f"--{_flag(name)}: {value} m/s is outside [{lo:g}, {hi:g}] m/s")
        lo, hi = ANGLE_BOUNDS_DEG
        if not (math.isfinite(self.angle_deg) and lo <= self.angle_deg <= hi):
            raise InputError(f"--angle: {self.angle_deg} degrees is outside [{lo:g}, {hi:g}]")
        if self.priority not in PRIORITIES:
            raise InputError(f"--priority: {self.priority!r} is not one of {', '.join(PRIORITIES)}")


def _flag(field_name: str) -> str:
    return field_name.rsplit("_", 1)[0].replace("_", "-")


def sumo_binary(name: str) -> Path:
    """Path to a SUMO tool (netconvert, sumo-gui) shipped with the eclipse-sumo wheel."""
    import sumo  # the eclipse-sumo wheel

    return Path(sumo.SUMO_HOME) / "bin" / name


def _plain_xml(params: NetParams) -> tuple[str, str]:
    a = math.radians(params.angle_deg)
    equal = params.priority == "equal"
    merge_priority = MAIN_EDGE_PRIORITY if equal else MERGE_EDGE_PRIORITY
    nodes = [
        ("main_start", -params.main_length_m, 0.0, "priority"),
        (
            "merge_start",
            -params.merge_length_m * math.cos(a),
            -params.merge_length_m * math.sin(a),
            "priority",
        ),
        (MERGE_JUNCTION, 0.0, 0.0, "zipper" if equal else "priority"),
        ("out_end", params.out_length_m, 0.0, "priority"),
    ]
    node_xml = (
        "<nodes>\n"
        + "".join(f'  <node id="{n}" x="{x:.3f}" y="{y:.3f}" type="{t}"/>\n' for n, x, y, t in nodes)
        + "</nodes>\n"
    )
    edges = [
        (
            MAIN_EDGE,
            "main_start",
            MERGE_JUNCTION,
            params.main_length_m,
            params.main_speed_mps,
            MAIN_EDGE_PRIORITY,
        ),
        (
            MERGE_EDGE,
            "merge_start",
            MERGE_JUNCTION,
            params.merge_length_m,
            params.merge_speed_mps,
            merge_priority,
        ),
        (OUT_EDGE, MERGE_JUNCTION, "out_end", params.out_length_m, params.out_speed_mps, MAIN_EDGE_PRIORITY),
    ]
    edge_xml = (
        "<edges>\n"
        + "".join(
            f'  <edge id="{e}" from="{f}" to="{t}" numLanes="1" speed="{v}" priority="{p}" length="{length}"/>\n'
            for e, f, t, length, v, p in edges
        )
        + "</edges>\n"
    )
    return node_xml, edge_xml


PLAIN_MARK = "<!-- written by idas-sumo beside its net; replaced when that net is written again -->\n"
"""The first line of every plain XML file written here: a file without it is the user's, never replaced."""
NET_SUFFIX = ".net.xml"


def check_net_out(out: Path, kinds: Sequence[str], force: bool = False) -> None:
    """Refuse to write the net ``out`` (and its ``<stem>.<kind>.xml`` beside it) where a file the tool
    did not write would be replaced (unless ``force``), inside the installed package, or under a name
    that is not ``*.net.xml`` (its plain XML would land beside it as ``notes.py.nod.xml``)."""
    if out.is_dir():
        raise InputError(f"--out {out}: is a directory, expected a .net.xml file name")
    if not out.name.endswith(NET_SUFFIX) or out.name == NET_SUFFIX:
        raise InputError(f"--out {out}: a net's file name ends in {NET_SUFFIX}, e.g. sumo_nets/my.net.xml")
    stem = out.name.removesuffix(NET_SUFFIX)
    claim_output_file(out, force, lambda p: _written_by_netconvert(p, f"{stem}.nod.xml"))
    for kind in kinds:
        claim_output_file(out.with_name(f"{stem}.{kind}.xml"), force, _has_plain_mark)


def _head(path: Path, size: int = 4096) -> str:
    try:
        with path.open("rb") as f:
            return f.read(size).decode("utf-8", "replace")
    except OSError:
        return ""


def _written_by_netconvert(path: Path, nodes: str) -> bool:
    """A net netconvert built from the plain XML beside it (its header names ``nodes`` as its node file)."""
    head = _head(path)
    return "netconvert" in head and any(
        value == nodes or value.endswith("/" + nodes) for value in _node_files(head)
    )


def _node_files(head: str) -> list[str]:
    marker = '<node-files value="'
    return [part.split('"', 1)[0] for part in head.split(marker)[1:]]


def _has_plain_mark(path: Path) -> bool:
    return _head(path, len(PLAIN_MARK)) == PLAIN_MARK


def write_plain_xml(out: Path, plain: Sequence[tuple[str, str]], force: bool = False) -> list[Path]:
    """Check that the net ``out`` can be written there (``check_net_out``), then write each (kind, text)
    of ``plain`` beside it as ``<stem>.<kind>.xml`` (atomically, marked ``PLAIN_MARK``); the files
    written. A place that cannot hold files is an InputError naming ``--out``; a full disk is an
    OSError (exit 1)."""
    check_net_out(out, [kind for kind, _ in plain], force)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"--out {out}: cannot create directory {out.parent} ({err.strerror})") from None
    if not os.access(out.parent, os.W_OK):
        raise InputError(f"--out {out}: directory {out.parent} is not writable")
    stem = out.name.removesuffix(NET_SUFFIX)
    written = []
    for kind, text in plain:
        path = out.with_name(f"{stem}.{kind}.xml")
        try:
            with atomic_open(path) as f:
                f.write(text if text.startswith(PLAIN_MARK) else PLAIN_MARK + text)
        except OSError as err:
            if err.errno not in _BAD_PLACE_ERRNOS:
                raise  # a full disk or an I/O error: a runtime failure (exit 1), named by the CLI
            raise InputError(f"--out {out}: cannot write {path} ({err.strerror})") from None
        written.append(path)
    return written


def generate_net(out_path: str | Path, params: NetParams = NetParams(), force: bool = False) -> Path:
    """Write the merge network to ``out_path`` (atomically) and keep its plain XML beside it; a file
    the tool did not write is replaced only with ``force`` (``check_net_out``)."""
    out = Path(out_path)
    node_xml, edge_xml = _plain_xml(params)
    nod, edg = write_plain_xml(out, [("nod", node_xml), ("edg", edge_xml)], force)
    with atomic_path(out) as tmp:
        cmd = [
            str(sumo_binary("netconvert")),
            "--node-files",
            str(nod),
            "--edge-files",
            str(edg),
            "--output-file",
            str(tmp),
            "--no-turnarounds",
            "true",
            "--junctions.corner-detail",
            "5",
            "--no-warnings",
            "true",
        ]
        result = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if result.returncode != 0:
            raise SimulationError(f"netconvert failed: {result.stderr.strip().splitlines()[-1:]}")
    return out


@dataclass(frozen=True)
class RoadInfo:
    """An edge of the merge network as read back by sumolib."""

    edge_id: str
    length_m: float
    speed_limit_mps: float
    priority: int
    via_length_m: float = 0.0
    """Length of the junction-internal lane from this road onto the outgoing road (0 for that road)."""


@dataclass(frozen=True)
class MergeNet:
    """A validated two-road merge: two incoming roads, one outgoing road, one merge junction."""

    path: Path
    main: RoadInfo
    merge: RoadInfo
    out: RoadInfo
    junction_id: str


def load_sumo_net(path: str | Path) -> Any:
    """A SUMO network file read by sumolib (junction-internal lanes included); every problem with the
    file is one InputError naming it."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: net file not found")
    if p.is_dir():
        raise InputError(f"{p}: is a directory, expected a .net.xml file")
    if not p.is_file():  # reading a FIFO blocks until someone writes to it
        raise InputError(f"{p}: not a regular file (a FIFO, device or socket), expected a .net.xml file")
    if not os.access(p, os.R_OK):
        raise InputError(f"{p}: net file not readable (permission denied)")
    import xml.etree.ElementTree as ET

    try:
        root = ET.parse(p).getroot()
    except ET.ParseError as err:
        raise InputError(f"{p}: not valid XML ({err})") from None
    if root.tag != "net":
        raise InputError(f"{p}: not a SUMO network (root element <{root.tag}>, expected <net>)")
    import sumolib

    try:
        return sumolib.net.readNet(str(p), withInternal=True)
    except Exception as err:  # sumolib raises many types on broken nets
        raise InputError(f"{p}: sumolib cannot read the network ({err})") from None


def read_merge_net(path: str | Path) -> MergeNet:
    """Read and validate a merge network; every problem is one InputError naming the file."""
    p = Path(path)
    net = load_sumo_net(p)
    junctions = [
        n for n in net.getNodes() if len([e for e in n.getIncoming() if e.getFunction() != "internal"]) >= 2
    ]
    if not junctions:
        raise InputError(f"{p}: no merge junction (a node with two incoming roads) in the network")
    if len(junctions) > 1:
        raise InputError(
            f"{p}: {len(junctions)} junctions with several incoming roads; expected exactly one merge"
        )
    junction = junctions[0]
    kind = str(junction.getType())
    if kind.startswith("traffic_light") or kind.startswith("rail_"):
        # A signal decides who goes: the merge the scenarios pose (cars negotiating the gap) is gone,
        # and the results would still look like an ordinary evaluation.
        raise InputError(
            f"{p}: the merge junction {junction.getID()!r} is a signal ({kind}); "
            "the scenarios need an unsignalled merge (e.g. type priority, as netgen makes)"
        )
    incoming = [e for e in junction.getIncoming() if e.getFunction() != "internal"]
    outgoing = [e for e in junction.getOutgoing() if e.getFunction() != "internal"]
    if len(incoming) != 2:
        raise InputError(f"{p}: the merge junction has {len(incoming)} incoming roads, expected 2")
    if len(outgoing) != 1:
        raise InputError(f"{p}: the merge junction has {len(outgoing)} outgoing roads, expected 1")
    for edge in [*incoming, *outgoing]:
        if edge.getLaneNumber() != 1:
            raise InputError(f"{p}: edge {edge.getID()!r} has {edge.getLaneNumber()} lanes, expected 1")
    out_edge = outgoing[0]
    for edge in incoming:
        if not edge.getConnections(out_edge):
            raise InputError(
                f"{p}: no connection from {edge.getID()!r} to {out_edge.getID()!r}: route not drivable"
            )
    # Main = the road with right of way: higher SUMO priority, then the higher speed limit, then the
    # straighter road (a zipper merge with equal limits).
    main_edge, merge_edge = sorted(incoming, key=lambda e: road_rank(e, out_edge), reverse=True)

    def info(edge: Any) -> RoadInfo:
        via_length = 0.0
        connections = edge.getConnections(out_edge) if edge is not out_edge else []
        if connections and connections[0].getViaLaneID():
            via_length = float(net.getLane(connections[0].getViaLaneID()).getLength())
        return RoadInfo(
            edge.getID(), float(edge.getLength()), float(edge.getSpeed()), int(edge.getPriority()), via_length
        )

    return MergeNet(p, info(main_edge), info(merge_edge), info(out_edge), junction.getID())


def turn_deg(from_lane: Any, to_lane: Any) -> float:
    """How far a car turns going from the end of ``from_lane`` onto ``to_lane``, degrees in [0, 180]."""
    (ax, ay), (bx, by) = from_lane.getShape()[-2:]
    (cx, cy), (dx, dy) = to_lane.getShape()[:2]
    turn = math.degrees(math.atan2(dy - cy, dx - cx) - math.atan2(by - ay, bx - ax))
    return abs((turn + 180.0) % 360.0 - 180.0)


def road_rank(edge: Any, out_edge: Any) -> tuple[int, float, float]:
    """Sort key of an incoming road at a merge, highest first for the main road: its SUMO priority,
    its speed limit, then how straight it runs on into ``out_edge``."""
    return (
        int(edge.getPriority()),
        float(edge.getSpeed()),
        -turn_deg(edge.getLanes()[0], out_edge.getLanes()[0]),
    )


def describe(net: MergeNet) -> str:
    return (
        f"{net.path}: main {net.main.edge_id} {net.main.length_m:.1f} m @ {net.main.speed_limit_mps:g} m/s, "
        f"merge {net.merge.edge_id} {net.merge.length_m:.1f} m @ {net.merge.speed_limit_mps:g} m/s, "
        f"out {net.out.edge_id} {net.out.length_m:.1f} m @ {net.out.speed_limit_mps:g} m/s"
    )


__all__ = [
    "PRIORITIES",
    "MergeNet",
    "NetParams",
    "RoadInfo",
    "check_net_out",
    "describe",
    "generate_net",
    "load_sumo_net",
    "read_merge_net",
    "road_rank",
    "turn_deg",
    "write_plain_xml",
]
