"""K disjoint copies of one SUMO network in one network file, so one SUMO run steps K scenarios at once.

libsumo holds one simulation per process. Instead of K processes, ``BatchBackend`` (sim/batch.py) runs
one simulation over a network made of K copies of the merge network, one scenario per copy. The copies
share no junction and no lane, and SUMO's driving here has no randomness (sigma 0, speedDev 0), so
every copy moves exactly as its scenario alone on the source network.

How a copy is made, for any ``.net.xml``: netconvert reads the source with ``--prefix c{k}_`` (every
edge and junction id, hence every lane and junction-internal id, gets the prefix) and ``--offset.y``
(copy k lies k spacings above the source, the spacing larger than the source's bounding box), then one
more netconvert merges the K copies. Normalisation is off in both steps so copy 0 keeps the source's
coordinates. Reading a net, netconvert recomputes junction shapes and junction-internal lanes; on a
shifted copy the coordinates round differently in binary, and at one of netconvert's thresholds the
result changes (on a 45 degree merge some copies' internal lanes came out longer). So the copies
are built from the source with its internal lanes pinned (``pin_internal_lanes``). A junction's
outline may still come out otherwise in a copy: the cars drive on the lanes (on a 45 degree net, the
same cars in copies with either outline drove identical trajectories, collisions on junctions checked).

The result is checked with sumolib against the source: every edge of every copy, the junction-internal
ones included, has the source's lanes with the same lengths and speed limits, the same priority and
function, and the same connections. Any difference is an ``UnfaithfulCopies`` error. A net that no copy
reproduces (one an older netconvert wrote: SUMO's 2018 ``A10KW`` example comes back with every edge
2.5 m shorter) runs one episode at a time on the file itself instead (``copies_run``; the engine's
results do not depend on K).

Built nets are cached by (source file content, K, SUMO version) in ``IDAS_SUMO_CACHE`` (else
``$XDG_CACHE_HOME/idas_sumo/nets``, else ``~/.cache/idas_sumo/nets``); a net is checked before it
enters the cache and is written atomically, so concurrent workers building the same net are safe
(the last rename wins, both files are the same). Before a process first uses a cached net it checks
it again (``cached_file_ok``: its digest, faithful to the source, SUMO loads it in a child process):
an edited file, even with its digest rewritten, is built again instead of crashing SUMO.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from idas_sumo.errors import InputError, SimulationError, SumoRefusedInput
from idas_sumo.io_utils import atomic_open, atomic_path, file_digest, remove_stale_temps
from idas_sumo.sim.merge_detect import Approach, MergeSite, RouteLane, as_site
from idas_sumo.sim.netgen import MergeNet, sumo_binary

log = logging.getLogger(__name__)
CACHE_ENV_VAR = "IDAS_SUMO_CACHE"
CACHE_FORMAT = 2
"""Bump when the way copies are built changes: older cached nets are then not reused."""
COPY_MARGIN_M = 100.0
"""Free space between two copies' bounding boxes (copies never touch, and sumo-gui shows them apart)."""
MAX_COPIES = 4096
STALE_TEMP_S = 3600.0
"""A temp file in the cache this old is a killed build's (a live build takes seconds to minutes)."""


def copy_prefix(k: int, copies: int) -> str:
    """The id prefix of copy ``k`` of ``copies``: ``c{k}_``, k zero-padded to the width of ``copies - 1``.

    Zero-padding keeps string order equal to copy order (SUMO lists vehicles sorted by id), and gives
    the plain ``c{k}_`` for up to 10 copies.
    """
    width = len(str(max(copies - 1, 0)))
    return f"c{k:0{width}d}_"


def global_edge_id(prefix: str, local_edge_id: str) -> str:
    """The id of a source edge in the copy with ``prefix``.

    netconvert prefixes junction ids, and a junction-internal edge is named ``:JUNCTION_n``: its
    prefix goes after the colon.
    """
    if local_edge_id.startswith(":"):
        return f":{prefix}{local_edge_id[1:]}"
    return prefix + local_edge_id


def prefixed_site(site: MergeSite, prefix: str, path: Path) -> MergeSite:
    """``site`` in a multi-copy net (file ``path``) as the copy whose ids carry ``prefix``: every edge
    id (a junction-internal one after its colon) and the junction id."""

    def lanes(xs: tuple[RouteLane, ...]) -> tuple[RouteLane, ...]:
        return tuple(dataclasses.replace(x, edge_id=global_edge_id(prefix, x.edge_id)) for x in xs)

    def approach(a: Approach) -> Approach:
        return dataclasses.replace(a, lanes=lanes(a.lanes), through=lanes(a.through))

    return dataclasses.replace(
        site,
        path=path,
        junction_id=prefix + site.junction_id,
        main=approach(site.main),
        merge=approach(site.merge),
        out=lanes(site.out),
    )


def default_cache_dir() -> Path:
    """Where built multi-copy nets are kept (``IDAS_SUMO_CACHE`` overrides)."""
    explicit = os.environ.get(CACHE_ENV_VAR)
    if explicit:
        return Path(explicit).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "idas_sumo" / "nets"


def _sumo_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("eclipse-sumo")
    except PackageNotFoundError:  # SUMO from elsewhere: its netconvert path still identifies it
        return str(sumo_binary("netconvert"))


def cache_key(source: Path, copies: int) -> str:
    """Hex digest naming the K-copy net of ``source`` (its bytes, K, SUMO version, build format)."""
    h = hashlib.sha256()
    h.update(source.read_bytes())
    h.update(f"\0copies={copies}\0sumo={_sumo_version()}\0format={CACHE_FORMAT}".encode())
    return h.hexdigest()


# -- reading a net for the check --------------------------------------------------------------------


@dataclass(frozen=True)
class _EdgeFacts:
    function: str
    priority: int
    lanes: tuple[tuple[float, float], ...]
    """(length m, speed limit m/s) per lane, by index."""
    connections: tuple[tuple[int, str, int, str], ...]
    """(from lane, to edge, to lane, via lane) per outgoing connection, sorted."""


def _edge_facts(path: Path) -> dict[str, _EdgeFacts]:
    """Every edge (junction-internal ones included) of a net file, as the check compares them."""
    import sumolib

    try:
        net = sumolib.net.readNet(str(path), withInternal=True)
    except Exception as err:  # sumolib raises many types on broken nets
        raise InputError(f"{path}: sumolib cannot read the network ({err})") from None
    facts: dict[str, _EdgeFacts] = {}
    for edge in net.getEdges(withInternal=True):
        lanes = tuple((float(lane.getLength()), float(lane.getSpeed())) for lane in edge.getLanes())
        connections = sorted(
            (
                int(c.getFromLane().getIndex()),
                str(c.getTo().getID()),
                int(c.getToLane().getIndex()),
                str(c.getViaLaneID() or ""),
            )
            for targets in edge.getOutgoing().values()
            for c in targets
        )
        facts[str(edge.getID())] = _EdgeFacts(
            str(edge.getFunction()), int(edge.getPriority()), lanes, tuple(connections)
        )
    return facts


def _bounding_box(path: Path) -> tuple[float, float, float, float]:
    import sumolib

    net = sumolib.net.readNet(str(path), withInternal=True)
    xmin, ymin, xmax, ymax = net.getBoundary()
    return float(xmin), float(ymin), float(xmax), float(ymax)


def _renamed(facts: _EdgeFacts, prefix: str) -> _EdgeFacts:
    def via(lane_id: str) -> str:
        return global_edge_id(prefix, lane_id) if lane_id else ""

    return dataclasses.replace(
        facts,
        connections=tuple(
            (fl, global_edge_id(prefix, to), tl, via(v)) for fl, to, tl, v in facts.connections
        ),
    )


class UnfaithfulCopies(SimulationError):
    """The K-copy net differs from its source (``check_copies``)."""


def check_copies(source: Path, built: Path, copies: int) -> None:
    """Raise ``UnfaithfulCopies`` unless ``built`` holds exactly ``copies`` faithful copies of ``source``."""
    want = _edge_facts(source)
    got = _edge_facts(built)
    problems: list[str] = []
    if len(got) != copies * len(want):
        problems.append(f"{len(got)} edges, expected {copies} x {len(want)}")
    for k in range(copies):
        prefix = copy_prefix(k, copies)
        for edge_id, facts in want.items():
            gid = global_edge_id(prefix, edge_id)
            if gid not in got:
                problems.append(f"edge {gid!r} missing")
            elif got[gid] != _renamed(facts, prefix):
                problems.append(f"edge {gid!r} differs from {edge_id!r}: {got[gid]} vs {facts}")
    if problems:
        shown = "; ".join(problems[:3]) + (f" (and {len(problems) - 3} more)" if len(problems) > 3 else "")
        raise UnfaithfulCopies(f"the {copies}-copy net of {source} is not faithful: {shown}")


# -- trusting the cache -----------------------------------------------------------------------------

LOAD_CHECK_TIMEOUT_S = 120.0
"""How long SUMO may take to load a cached net in the check (a net of the cache loads in well under 1 s)."""
_CHECKED: set[tuple[str, str]] = set()
"""Cached nets (path, SHA-256) this process has checked: each is checked once per process."""


def sumo_load_problem(path: Path) -> str | None:
    """Why SUMO cannot load the net ``path``, tried in a child process; None when it loads cleanly.

    libsumo reads a net inside this process, and a malformed one can crash it with no message (a net
    whose lanes have empty shapes is a segfault), so a cached file is loaded by a child first."""
    binary = sumo_binary("sumo")
    cmd = [
        str(binary),
        "--net-file",
        str(path),
        "--end",
        "0",
        "--no-step-log",
        "true",
        "--no-warnings",
        "true",
    ]
    env = {**os.environ, "SUMO_HOME": str(binary.parents[1])}
    try:
        result = subprocess.run(
            cmd, capture_output=True, text=True, timeout=LOAD_CHECK_TIMEOUT_S, env=env, check=False
        )
    except subprocess.TimeoutExpired:
        return f"SUMO took over {LOAD_CHECK_TIMEOUT_S:.0f} s to load it"
    except OSError as err:
        return f"cannot run {binary} ({err.strerror})"
    if result.returncode < 0:
        return f"SUMO crashed loading it (signal {-result.returncode})"
    if result.returncode != 0:
        errors = [ln.strip() for ln in result.stderr.splitlines() if ln.startswith("Error")]
        return errors[-1] if errors else f"SUMO exited with {result.returncode}"
    return None


def cached_file_ok(path: Path, digest: Path, check: Callable[[Path], object]) -> bool:
    """Whether the cached net ``path`` may be used: it has the SHA-256 written beside it when it was
    built (``digest``), and, once per process, it still passes the checks it passed then (``check``
    raises on a bad net; no DTD, which no net written by SUMO has; SUMO loads it in a child process).
    The digest alone is not enough: an edited file with its digest rewritten crashed SUMO. A file
    that fails is logged and left for the caller to build again."""
    if not (path.is_file() and digest.is_file()):
        return False
    sha = file_digest(path)
    if digest.read_text().strip() != sha:
        return False
    if (str(path), sha) in _CHECKED:
        return True
    problem = _cached_file_problem(path, check)
    if problem is not None:
        log.warning("%s: the cached net fails its check (%s); building it again", path, problem)
        return False
    _CHECKED.add((str(path), sha))
    return True


def _cached_file_problem(path: Path, check: Callable[[Path], object]) -> str | None:
    if b"<!DOCTYPE" in path.read_bytes():  # entities (and their bombs) live in a DTD
        return "it declares a DTD"
    try:
        check(path)
    except Exception as err:  # an edited file breaks the readers in any way: each is a failed check
        return str(err) or type(err).__name__
    return sumo_load_problem(path)


def remember_checked(path: Path) -> None:
    """``path`` was just built and checked here: no need to check it again in this process."""
    _CHECKED.add((str(path), file_digest(path)))


# -- building ---------------------------------------------------------------------------------------


def _netconvert(args: list[str], refused_source: Path | None = None) -> None:
    """Run netconvert; with ``refused_source`` a failure means SUMO refused the user's net (bad input)."""
    cmd = [str(sumo_binary("netconvert")), *args, "--no-warnings", "true"]
    result = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if result.returncode != 0:
        lines = [ln.strip() for ln in result.stderr.splitlines() if ln.strip()]
        errors = [ln for ln in lines if ln.startswith("Error")]
        reason = "; ".join(errors[-2:]) if errors else (lines or ["no message"])[-1]
        if refused_source is not None:
            raise SumoRefusedInput(f"SUMO could not load {refused_source}: {reason}")
        raise SimulationError(f"netconvert failed: {reason}")


def pin_internal_lanes(source: Path, out: Path) -> None:
    """Write ``source`` to ``out`` with its junction-internal lanes pinned to the source's.

    netconvert, reading a net, recomputes each junction-internal lane from the lanes it joins. A copy
    is the source shifted by ``--offset.y``: its coordinates round differently in binary, and where a
    computation sits at one of netconvert's thresholds it goes the other way. A 45 degree merge is one:
    the merging lane meets the outgoing lane at the angle where netconvert switches how it curves the
    internal lane, and some copies got 7.70 m (9.23 m/s) for the source's 7.49 m (9.11 m/s); a car's
    distance to the merge point is measured along that lane. Here every connection between two
    ordinary edges through one internal lane gets that lane's ``shape``, ``length`` and ``speed`` as
    its own (values the source gives already are kept), which netconvert takes as given; the strings
    are the source's, so nothing is rounded again.

    Left as they were, because pinning them made faithful copies unfaithful: an internal lane that an
    internal junction splits in two (netconvert puts the split elsewhere on a custom shape), and the
    junctions' shapes (ordinary edges are cut where they meet the junction's shape, and at the
    shape's rounded coordinates their lengths moved by 0.01 m). ``check_copies`` checks the result.
    """
    import xml.etree.ElementTree as ET

    ET.register_namespace("xsi", "http://www.w3.org/2001/XMLSchema-instance")
    try:
        tree = ET.parse(source)
    except ET.ParseError as err:
        raise InputError(f"{source}: not valid XML ({err})") from None
    root = tree.getroot()
    lanes = {
        lane.get("id", ""): lane
        for edge in root.iter("edge")
        if edge.get("function") == "internal"
        for lane in edge.iter("lane")
    }
    split = {  # internal edges an internal junction splits: a connection leaves them through another
        c.get("from", "")
        for c in root.iter("connection")
        if c.get("from", "").startswith(":") and c.get("via")
    }
    for connection in root.iter("connection"):
        lane = lanes.get(connection.get("via", ""))
        if lane is None or connection.get("from", "").startswith(":"):
            continue
        if connection.get("via", "").rpartition("_")[0] in split:
            continue
        for name in ("shape", "length", "speed"):
            value = lane.get(name)
            if value is not None and connection.get(name) is None:
                connection.set(name, value)
    tree.write(out, encoding="UTF-8", xml_declaration=True)


def _build(source: Path, copies: int, out: Path, workdir: Path) -> None:
    xmin, ymin, xmax, ymax = _bounding_box(source)
    del xmin, xmax
    spacing = float(int((ymax - ymin + COPY_MARGIN_M) / 100.0) + 1) * 100.0  # whole hundreds of metres
    pinned = workdir / "pinned.net.xml"
    pin_internal_lanes(source, pinned)
    parts: list[str] = []
    for k in range(copies):
        part = workdir / f"copy{k}.net.xml"
        _netconvert(
            [
                "--sumo-net-file",
                str(pinned),
                "--prefix",
                copy_prefix(k, copies),
                "--offset.y",
                f"{k * spacing:.2f}",
                "--offset.disable-normalization",
                "true",
                "--output-file",
                str(part),
            ],
            refused_source=source,
        )
        parts.append(str(part))
    _netconvert(
        [
            "--sumo-net-file",
            ",".join(parts),
            "--offset.disable-normalization",
            "true",
            "--output-file",
            str(out),
        ]
    )


def build_copies(source: str | Path, copies: int, cache_dir: str | Path | None = None) -> Path:
    """The path of a checked net file holding ``copies`` disjoint copies of ``source`` (built or cached)."""
    src = Path(source)
    if not isinstance(copies, int) or not 1 <= copies <= MAX_COPIES:
        raise InputError(f"copies: {copies!r} is not a whole number in [1, {MAX_COPIES}]")
    if not src.is_file():
        raise InputError(f"{src}: net file not found")
    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    try:
        cache.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"{cache}: cannot create the net cache directory ({err.strerror})") from None
    remove_stale_temps(cache, older_than_s=STALE_TEMP_S)  # builds killed before their rename
    out = _cached_path(src, copies, cache)
    digest = out.with_name(out.name + ".sha256")
    # A cached net is used only with the digest written when it was built and still faithful to the
    # source: a truncated or edited cache file was blamed on the user's net, ran with other roads, or
    # crashed SUMO.
    if cached_file_ok(out, digest, lambda built: check_copies(src, built, copies)):
        return out
    workdir = Path(tempfile.mkdtemp(prefix="idas_sumo_multinet_"))
    try:
        with atomic_path(out) as tmp:
            _build(src, copies, tmp, workdir)
            check_copies(src, tmp, copies)
            with atomic_open(digest) as f:
                f.write(file_digest(tmp) + "\n")
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    remember_checked(out)
    return out


def _cached_path(source: Path, copies: int, cache: Path) -> Path:
    return cache / f"{cache_key(source, copies)[:24]}-k{copies}.net.xml"


def copies_run(source: str | Path, copies: int, cache_dir: str | Path | None = None) -> bool:
    """Whether ``copies`` faithful copies of ``source`` can run (built and cached now if needed); False
    for a net whose copies ``check_copies`` refuses, remembered beside the cache's nets (a
    ``.unfaithful`` file with the reason) so the build is not tried again."""
    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    src = Path(source)
    if src.is_file() and _cached_path(src, copies, cache).with_suffix(".unfaithful").is_file():
        return False
    try:
        build_copies(src, copies, cache)
    except UnfaithfulCopies as err:
        with atomic_open(_cached_path(src, copies, cache).with_suffix(".unfaithful")) as f:
            f.write(f"{err}\n")
        return False
    return True


# -- the merge network, K times ---------------------------------------------------------------------


@dataclass(frozen=True)
class MultiNet:
    """K copies of one merge site's network in one net file."""

    path: Path
    """The K-copy net file (in the cache)."""
    site: MergeSite
    """The merge as detected in the source net: copy-local ids and lengths."""
    copies: int
    edge_ids: tuple[str, ...]
    """Copy-local ids of every edge of the source, junction-internal ones included: the ordinary edges
    of the main approach, the merge approach and the road after the merge first, then the others
    sorted (``BatchStates.edge_index`` indexes this)."""

    def prefix(self, k: int) -> str:
        if not 0 <= k < self.copies:
            raise IndexError(f"copy {k} of a {self.copies}-copy net")
        return copy_prefix(k, self.copies)

    def copy_site(self, k: int) -> MergeSite:
        """Copy ``k``'s merge site (global edge and junction ids; ``path`` the K-copy file)."""
        return prefixed_site(self.site, self.prefix(k), self.path)

    @property
    def source(self) -> MergeNet:
        """The source as a ``MergeNet`` (only for a site of the T-junction's shape: ``as_merge_net``)."""
        return self.site.as_merge_net()

    def copy_net(self, k: int) -> MergeNet:
        """Copy ``k`` as a ``MergeNet`` (a site of the T-junction's shape only)."""
        return self.copy_site(k).as_merge_net()

    def edge_table(self) -> dict[str, tuple[int, int]]:
        """Global edge id -> (copy, index into ``edge_ids``), for every edge of every copy."""
        return {
            global_edge_id(copy_prefix(k, self.copies), e): (k, i)
            for k in range(self.copies)
            for i, e in enumerate(self.edge_ids)
        }


def multi_net(
    source: MergeSite | MergeNet | str | Path, copies: int, cache_dir: str | Path | None = None
) -> MultiNet:
    """K copies of a merge site's network (a ``MergeSite``, a ``MergeNet`` or a ``.net.xml`` with one
    merge), built once and cached."""
    site = as_site(source)
    path = build_copies(site.path, copies, cache_dir)
    roads = tuple(
        dict.fromkeys(
            (*site.main.edge_ids, *site.merge.edge_ids, *(r.edge_id for r in site.out if not r.internal))
        )
    )
    others = sorted(set(_edge_ids(site.path)) - set(roads))
    return MultiNet(path, site, copies, (*roads, *others))


def _edge_ids(path: Path) -> list[str]:
    import sumolib

    net: Any = sumolib.net.readNet(str(path), withInternal=True)
    return [str(e.getID()) for e in net.getEdges(withInternal=True)]


__all__ = [
    "CACHE_ENV_VAR",
    "MultiNet",
    "build_copies",
    "cache_key",
    "cached_file_ok",
    "check_copies",
    "copy_prefix",
    "default_cache_dir",
    "global_edge_id",
    "multi_net",
    "pin_internal_lanes",
    "prefixed_site",
]
