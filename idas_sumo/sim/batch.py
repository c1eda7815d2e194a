"""K merge scenarios in one in-process SUMO run, over a K-copy network (sim/multinet.py).

One ``libsumo.simulationStep()`` advances every copy. Copies share nothing, and SUMO drives without
randomness here, so each copy's vehicles move exactly as in a ``SumoBackend`` run of that scenario
alone (tests/test_sim_batch.py checks it vehicle by vehicle). Everything SUMO-facing is
``SumoBackend``'s: the route file's vTypes and vehicle lines, the SUMO options, the controlled
vehicles' speed mode, the stderr capture and error wrapping, and the one-simulation-per-process guard
(a ``BatchBackend`` occupies the same slot as a ``SumoBackend``).

Ids: copy ``k``'s vehicles and edges carry the prefix ``MultiNet.prefix(k)`` in SUMO (``c{k}_``, k
zero-padded from 11 copies on, so SUMO's id order is copy order);
events and states come back with copy-local ids plus the copy index, and commands take either.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from idas_sumo.errors import InputError, SimulationError, SumoRefusedInput
from idas_sumo.sim import backend as _backend
from idas_sumo.sim.backend import (
    CONTROLLED_SPEED_MODE,
    LANE_KEEPING_MODE,
    SUMO_DEFAULT_SPEED_MODE,
    RouteScenario,
    StepEvents,
    SumoBackend,
    VehicleStates,
    _route_lines,
    _swig,
    _vehicle_lines,
    _vtype_lines,
    controlled_top_speed,
    has_lane_changes,
)
from idas_sumo.sim.merge_detect import MergeSite
from idas_sumo.sim.multinet import MultiNet, multi_net
from idas_sumo.sim.netgen import MergeNet

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


# -- the route file ---------------------------------------------------------------------------------


def batch_route_xml(scenarios: Sequence[RouteScenario], net: MultiNet) -> str:
    """One route file for all copies: ``SumoBackend``'s vTypes and vehicle lines, ids and routes per copy.

    Vehicles are sorted by departure (SUMO reads route files in time order); within one copy they keep
    ``SumoBackend``'s order (departure, then id), so each copy inserts its cars in the same order.
    """
    routes: list[str] = []
    keyed: list[tuple[float, int, int, str]] = []
    for k, scenario in enumerate(scenarios):
        p = net.prefix(k)
        site = net.copy_site(k)
        routes += _route_lines(site, p)
        # _vehicle_lines writes the vehicles sorted by (depart, id): the same sort here pairs keys with lines.
        order = sorted(scenario.vehicles, key=lambda v: (v.depart_s, v.id))
        lines = _vehicle_lines(scenario.vehicles, site, p)
        assert len(lines) == len(order), "one vehicle line per vehicle"
        keyed += [(v.depart_s, k, i, ln) for i, (v, ln) in enumerate(zip(order, lines, strict=True))]
    keyed.sort(key=lambda t: (t[0], t[1], t[2]))
    return (
        "\n".join(
            [
                "<routes>",
                *_vtype_lines(has_lane_changes(net.site), controlled_top_speed(net.site)),
                *routes,
                *(t[3] for t in keyed),
                "</routes>",
            ]
        )
        + "\n"
    )


# -- results ----------------------------------------------------------------------------------------


@dataclass
class BatchStepEvents:
    """What happened in one step, per copy (copy-local ids; each copy's ``time_s`` is ``time_s``)."""

    time_s: float
    copies: list[StepEvents] = field(default_factory=list)


@dataclass(frozen=True)
class BatchStates:
    """Every vehicle of every copy, grouped by copy in ascending order (arrays align with ``ids``).

    Within one copy the order is ``SumoBackend.vehicle_states``'s for that scenario alone.
    """

    ids: tuple[str, ...]
    """Copy-local vehicle ids."""
    copy: IntArray
    vehicle: IntArray
    """Each vehicle's index in its copy's scenario (``Scenario.vehicles``; -1: not from the scenario)."""
    edge: tuple[str, ...]
    """Copy-local edge ids (junction-internal ones start with a colon)."""
    edge_index: IntArray
    """Index of ``edge`` in ``MultiNet.edge_ids`` (-1 for an edge not in the source net)."""
    lane_pos_m: FloatArray
    speed_mps: FloatArray
    accel_mps2: FloatArray
    bounds: IntArray
    """Copy k's vehicles are rows ``bounds[k]:bounds[k + 1]`` (len = copies + 1)."""
    lane_index: IntArray | None = None
    """Each car's lane index on its edge, only on a merge whose approaches share edges
    (``VehicleStates.lane_index``)."""

    def of_copy(self, k: int) -> VehicleStates:
        """Copy ``k``'s vehicles as ``SumoBackend.vehicle_states`` gives them for its scenario alone."""
        lo, hi = int(self.bounds[k]), int(self.bounds[k + 1])
        return VehicleStates(
            self.ids[lo:hi],
            self.edge[lo:hi],
            self.lane_pos_m[lo:hi],
            self.speed_mps[lo:hi],
            self.accel_mps2[lo:hi],
            None if self.lane_index is None else self.lane_index[lo:hi],
        )


@dataclass(frozen=True)
class _IdLayout:
    """SUMO's vehicle id list as ``BatchStates`` gives it: local ids, copies, scenario indices, bounds, and
    the permutation that sorts the list by copy (None: it is sorted)."""

    ids: tuple[str, ...]
    copy: IntArray
    vehicle: IntArray
    bounds: IntArray
    order: IntArray | None


# -- the backend ------------------------------------------------------------------------------------


class BatchBackend:
    """Up to ``copies`` scenarios in the one SUMO simulation of this process."""

    def __init__(
        self,
        net: MergeSite | MergeNet | MultiNet,
        copies: int | None = None,
        seed: int = 0,
        extra_args: Sequence[str] = (),
        cache_dir: str | Path | None = None,
    ) -> None:
        """``net``: a ``MultiNet``, or a merge site (or ``MergeNet``) to copy ``copies`` times (built
        once, cached)."""
        if isinstance(net, MultiNet):
            if copies is not None and copies != net.copies:
                raise InputError(f"copies: {copies} given with a {net.copies}-copy net")
            self.net = net
        else:
            if copies is None:
                raise InputError("copies: needed to build a multi-copy net from a merge site")
            self.net = multi_net(net, copies, cache_dir)
        self.copies = self.net.copies
        # SumoBackend's own option list, on the K-copy file: one home for SUMO's options.
        self._options = SumoBackend(
            dataclasses.replace(self.net.site, path=self.net.path), seed=seed, extra_args=extra_args
        )
        self._prefixes = tuple(self.net.prefix(k) for k in range(self.copies))
        self._copy_range = np.arange(self.copies + 1, dtype=np.int64)
        # Global edge id -> (index into net.edge_ids, copy-local edge id).
        self._edge_map = {g: (i, self.net.edge_ids[i]) for g, (_, i) in self.net.edge_table().items()}
        self._running = False
        self._workdir: Path | None = None
        self._split: dict[str, tuple[int, str, int]] = {}
        """Global vehicle id -> (copy, local id, index in its scenario), for every vehicle of the loaded
        scenarios."""
        self._read_ids: tuple[str, ...] | None = None
        self._read_layout: _IdLayout | None = None
        """``vehicle_states``' split of the id list ``_read_ids``, kept while the same cars are on the road."""
        self._read_roads: list[str] | None = None
        self._read_edges: tuple[tuple[str, ...], IntArray] = ((), np.zeros(0, dtype=np.int64))
        """The copy-local edges and their indices of the SUMO edges ``_read_roads`` (kept while they stay)."""
        self._controlled: set[str] = set()
        self._released: set[str] = set()
        self._cleared: set[int] = set()
        """Copies emptied by ``clear_copy`` since the last reset."""
        self._active_copies = 0
        self._lane_keeping = has_lane_changes(self.net.site)
        self._read_lanes = bool(self.net.site.shared_lanes)

    # -- lifecycle -------------------------------------------------------------------------------
    def reset(self, scenarios: Sequence[RouteScenario], extra_args: Sequence[str] = ()) -> None:
        """(Re)load the K-copy net with scenario k in copy k (the insertion step is ``step``'s job).

        Fewer scenarios than copies leave the last copies empty. ``extra_args`` are SUMO options for
        this run only.
        """
        import tempfile

        if not 1 <= len(scenarios) <= self.copies:
            raise InputError(f"{len(scenarios)} scenarios for a {self.copies}-copy net (1 to {self.copies})")
        _backend.claim_slot(self, "close it before opening a BatchBackend")
        if self._workdir is None:
            self._workdir = Path(tempfile.mkdtemp(prefix="idas_sumo_batch_"))
        route_file = self._workdir / "batch.rou.xml"
        route_file.write_text(batch_route_xml(scenarios, self.net))
        args = [*self._options._args(route_file), *extra_args]
        try:
            _backend.start_or_load(args, self._running, self.net.path)
        except SumoRefusedInput:
            self._running = False
            _backend.hold_slot(None)
            raise
        self._running = True
        _backend.hold_slot(self)  # SumoBackend and make_backend now see this process's simulation as taken
        self._split = {
            self._prefixes[k] + v.id: (k, v.id, i)
            for k, s in enumerate(scenarios)
            for i, v in enumerate(s.vehicles)
        }
        self._read_ids = self._read_layout = None
        self._read_roads = None
        self._controlled = {
            self._prefixes[k] + vid for k, s in enumerate(scenarios) for vid in s.controlled_ids
        }
        self._released = set()
        self._cleared = set()
        self._active_copies = len(scenarios)

    def close(self) -> None:
        _backend.end_run(self, self._running, self._workdir)
        self._running = False
        self._workdir = None

    @property
    def running(self) -> bool:
        return self._running

    @property
    def active_copies(self) -> int:
        """How many copies the last reset filled (copies 0 .. active_copies - 1)."""
        return self._active_copies

    def global_id(self, copy: int, vehicle_id: str) -> str:
        return self._prefixes[copy] + vehicle_id

    def _local(self, global_id: str) -> tuple[int, str]:
        k, local, _ = self._split_id(global_id)
        return k, local

    def _split_id(self, global_id: str) -> tuple[int, str, int]:
        """(copy, local id, index in its scenario or -1)."""
        found = self._split.get(global_id)
        if found is not None:
            return found
        # A vehicle not from the scenarios (added by a tool): its copy is in its prefix.
        for k in range(self.copies - 1, -1, -1):
            if global_id.startswith(self._prefixes[k]):
                return k, global_id[len(self._prefixes[k]) :], -1
        raise SimulationError(f"vehicle {global_id!r} belongs to no copy of the net")

    # -- stepping --------------------------------------------------------------------------------
    def time_s(self) -> float:
        import libsumo

        return float(libsumo.simulation.getTime())

    def step(self) -> BatchStepEvents:
        """Advance every copy by one step; events per copy, with copy-local ids."""
        import libsumo

        simulation = libsumo.simulation
        try:
            libsumo.simulationStep()
        except (libsumo.TraCIException, libsumo.FatalTraCIError) as err:
            raise SimulationError(f"SUMO failed during a step: {err}") from None
        time_s = float(simulation.getTime())
        # (every field given, by position: collided, collision_pairs, departed, arrived, teleported, time_s;
        # StepEvents' default factories and keywords cost more, once per copy and step)
        events = [StepEvents(set(), [], [], [], [], time_s) for _ in range(self._active_copies)]
        cleared = self._cleared
        departed = simulation.getDepartedIDList()
        for vid in departed:
            k, local = self._local(vid)
            if k in cleared:  # a car of an emptied copy that just entered: gone again, unreported
                libsumo.vehicle.remove(vid)
                continue
            if vid in self._controlled:
                libsumo.vehicle.setSpeedMode(vid, CONTROLLED_SPEED_MODE)
            if self._lane_keeping:
                libsumo.vehicle.setLaneChangeMode(vid, LANE_KEEPING_MODE)
            events[k].departed.append(local)
        collided_global: set[str] = set()
        for collision in simulation.getCollisions():
            k, collider = self._local(collision.collider)
            k2, victim = self._local(collision.victim)
            if k != k2:
                raise SimulationError(
                    f"collision across copies ({collision.collider} and {collision.victim}): the net's "
                    "copies overlap"
                )
            collided_global.update((collision.collider, collision.victim))
            if k not in cleared:
                events[k].collision_pairs.append((collider, victim))
                events[k].collided.update((collider, victim))
        for vid in simulation.getArrivedIDList():
            if vid not in collided_global:
                k, local = self._local(vid)
                if k not in cleared:
                    events[k].arrived.append(local)
        for vid in simulation.getStartingTeleportIDList():
            k, local = self._local(vid)
            if k not in cleared:
                events[k].teleported.append(local)
        return BatchStepEvents(time_s, events)

    def vehicle_states(self) -> BatchStates:
        """Every vehicle's copy, edge, lane position, speed and acceleration.

        Read with the plain getters, called through libsumo's SWIG functions (``libsumo._libsumo``:
        the ``libsumo.vehicle`` methods are Python wrappers around them) and ``map`` into ``np.fromiter``.
        The cheapest of the ways benchmarks/sumo_read.py compares: subscriptions are filled inside
        ``simulationStep``, which they slow down, and cost more than these getters.

        The split of the ids into copies, local ids and scenario indices is kept while the id list stays
        the same (most steps: only an entry or an exit changes it), so a step pays one tuple comparison
        for it instead of a dictionary lookup per vehicle.
        """
        _libsumo = _swig()

        gids = _libsumo.vehicle_getIDList()
        n = len(gids)
        roads = list(map(_libsumo.vehicle_getRoadID, gids))
        lane_pos = np.fromiter(map(_libsumo.vehicle_getLanePosition, gids), np.float64, n)
        speed = np.fromiter(map(_libsumo.vehicle_getSpeed, gids), np.float64, n)
        accel = np.fromiter(map(_libsumo.vehicle_getAcceleration, gids), np.float64, n)
        lane_index = (
            np.fromiter(map(_libsumo.vehicle_getLaneIndex, gids), np.int64, n) if self._read_lanes else None
        )
        if gids != self._read_ids:  # cars entered or left since the last read: split the ids again
            self._read_layout = self._id_layout(gids)
            self._read_ids = gids
        layout = self._read_layout
        assert layout is not None
        if roads == self._read_roads:  # every car on the same edge as in the last read (most steps)
            edge, edge_index = self._read_edges
        else:
            edge_map = self._edge_map
            try:
                edge_indices, edges = zip(*map(edge_map.__getitem__, roads), strict=True) if n else ((), ())
            except KeyError:  # an edge not in the source net (cannot happen on a checked copy; kept raw)
                edge_indices, edges = zip(*((edge_map.get(r) or (-1, r)) for r in roads), strict=True)
            edge_index = np.array(edge_indices, dtype=np.int64)
            edge_index.flags.writeable = False
            edge = edges
            self._read_roads, self._read_edges = roads, (edge, edge_index)
        order = layout.order
        if order is not None:  # SUMO lists by id, so copies come in order; if not, sorted by copy
            lane_pos, speed, accel, edge_index = (
                lane_pos[order],
                speed[order],
                accel[order],
                edge_index[order],
            )
            edge = tuple(edge[i] for i in order.tolist())
            lane_index = None if lane_index is None else lane_index[order]
        return BatchStates(
            layout.ids,
            layout.copy,
            layout.vehicle,
            edge,
            edge_index,
            lane_pos,
            speed,
            accel,
            layout.bounds,
            lane_index,
        )

    def _id_layout(self, gids: tuple[str, ...]) -> _IdLayout:
        """``vehicle_states``' copy-local view of SUMO's id list (sorted by copy where it is not)."""
        if not gids:
            empty = np.zeros(0, dtype=np.int64)
            return _IdLayout((), empty, empty, np.zeros(self.copies + 1, np.int64), None)
        try:
            copies, ids, vehicles = zip(*map(self._split.__getitem__, gids), strict=True)
        except KeyError:  # a vehicle not from the scenarios (added by a tool)
            copies, ids, vehicles = zip(*map(self._split_id, gids), strict=True)
        copy = np.array(copies, dtype=np.int64)
        vehicle = np.array(vehicles, dtype=np.int64)
        order = None
        if (copy[1:] < copy[:-1]).any():
            order = np.argsort(copy, kind="stable")
            copy, vehicle = copy[order], vehicle[order]
            ids = tuple(ids[i] for i in order.tolist())
        bounds = copy.searchsorted(self._copy_range)
        for a in (copy, vehicle, bounds):
            a.flags.writeable = False  # handed out again with every read of the same cars
        return _IdLayout(ids, copy, vehicle, bounds, order)

    def set_speeds(
        self,
        vehicle_ids: Sequence[str],
        speeds_mps: npt.ArrayLike,
        copy: npt.ArrayLike | None = None,
    ) -> None:
        """Command the next step's speed of controlled vehicles (validated: finite, >= 0).

        ``copy`` None: ``vehicle_ids`` are global (prefixed) ids; else copy-local ids, ``copy[i]`` the
        copy of ``vehicle_ids[i]``.
        """
        import libsumo

        speeds = np.asarray(speeds_mps, dtype=np.float64)
        if speeds.shape != (len(vehicle_ids),):
            raise SimulationError(f"{speeds.shape} speeds for {len(vehicle_ids)} vehicles (a bug)")
        # Two reductions for the check (a NaN makes the minimum NaN; -0.0 passes, as before) ...
        if len(speeds) and not (speeds.min() >= 0 and speeds.max() < np.inf):
            i = int(np.flatnonzero(~np.isfinite(speeds) | (speeds < 0))[0])  # ... the first bad one named
            raise SimulationError(
                f"invalid speed command {speeds[i]!r} for vehicle {vehicle_ids[i]!r} (a bug, not an input)"
            )
        if copy is None:
            gids = list(vehicle_ids)
        else:
            prefixes = self._prefixes
            gids = [prefixes[k] + v for k, v in zip(np.asarray(copy).tolist(), vehicle_ids, strict=True)]
        _libsumo = _swig()

        values = speeds.tolist()
        try:  # the common case in one pass (setSpeed through SWIG directly, like the getters)
            deque(map(_libsumo.vehicle_setSpeed, gids, values), maxlen=0)
        except libsumo.TraCIException:
            # Some car is gone; setting a speed twice is harmless, so go again one by one.
            present = set(libsumo.vehicle.getIDList())
            for vid, v in zip(gids, values, strict=True):
                try:
                    _libsumo.vehicle_setSpeed(vid, v)
                except libsumo.TraCIException as err:
                    if vid in present:
                        raise SimulationError(f"SUMO refused the speed of vehicle {vid!r}: {err}") from None
                    # Removed by SUMO since the last step: that step reported it (collided or arrived).

    def release(self, vehicle_id: str, copy: int | None = None) -> None:
        """Hand a controlled vehicle back to SUMO's own driver model (after it finished).

        ``copy`` None: ``vehicle_id`` is global; else copy-local in that copy.
        """
        import libsumo

        vid = vehicle_id if copy is None else self._prefixes[copy] + vehicle_id
        if vid in self._controlled and vid not in self._released:
            libsumo.vehicle.setSpeedMode(vid, SUMO_DEFAULT_SPEED_MODE)
            libsumo.vehicle.setSpeed(vid, -1)
            self._released.add(vid)

    def remove(self, vehicle_id: str, copy: int) -> None:
        """Take copy ``copy``'s vehicle (copy-local id) off the road, as SUMO's ``--collision.action
        remove`` does (the engine's geometric collision check); one already gone is no error."""
        import contextlib

        import libsumo

        with contextlib.suppress(libsumo.TraCIException):
            libsumo.vehicle.remove(self._prefixes[copy] + vehicle_id)

    def clear_copy(self, copy: int) -> None:
        """Remove every vehicle of copy ``copy``, on the road or still to depart (its episode is over).

        An idle copy then costs SUMO nothing until the next ``reset``; the other copies are untouched.
        Removed vehicles are reported nowhere (neither arrived nor collided). SUMO loads a vehicle only
        when its departure comes, so one still to depart is removed in the step it enters.
        """
        import contextlib

        import libsumo

        if not 0 <= copy < self.copies:
            raise IndexError(f"copy {copy} of a {self.copies}-copy net")
        self._cleared.add(copy)
        for vid in libsumo.vehicle.getIDList():
            if self._local(vid)[0] == copy:
                with contextlib.suppress(libsumo.TraCIException):
                    libsumo.vehicle.remove(vid)

    def raw_call(self, domain: str, method: str, *args: Any) -> Any:
        """Escape hatch for tests and tools: call libsumo.<domain>.<method>(*args) (global ids)."""
        import libsumo

        return getattr(getattr(libsumo, domain), method)(*args)


__all__ = ["BatchBackend", "BatchStates", "BatchStepEvents", "batch_route_xml"]
