"""One SUMO run in this process through libsumo: start, insert a scenario, command speeds, report events.

libsumo holds one simulation per process and a second ``start`` silently replaces the first, so this
module owns a process-wide guard: a second open ``SumoBackend`` is refused with a clear error.
"""

from __future__ import annotations

import atexit
import contextlib
import math
import os
import shutil
import tempfile
import time
import typing
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from idas_sumo.errors import InputError, SimulationError, SumoRefusedInput
from idas_sumo.sim.frozen import built
from idas_sumo.sim.merge_detect import MergeSite, Side, as_site
from idas_sumo.sim.netgen import MergeNet
from idas_sumo.sim.rpc import CallBackServer, NoCallBack

STEP_LENGTH_S = 0.2  # SUMO's step, also the agents' decision period (5 Hz)
CONTROLLED_SPEED_MODE = 32  # every check off, right of way inside the junction ignored too (bit 5 inverted)
SUMO_DEFAULT_SPEED_MODE = 31
LANE_KEEPING_MODE = 0b10_0000_0001
"""SUMO lane-change mode of every car on a merge with multi-lane edges (set as it departs): strategic
changes only (bits 0-1: those its route needs, unless they conflict with a TraCI command), respecting
the other cars' gaps (bits 8-9 = 2); none to gain speed, keep right or make room. So no car leaves
the lanes the engine measures (a highway car never moves to the left lane: SUMO's default mode sent a
controlled highway car there at once, beside an on-ramp car), and the one change left is an on-ramp
car's, from the acceleration lane onto the highway's lane before its lane ends (blocked until the
end, SUMO stops it there and it changes when a gap comes). Not set on single-lane merges, where no
car can change lanes (the generated T-junction runs as it always did)."""
CONTROLLED_LC_ASSERTIVE = 20.0
"""How much smaller than SUMO's safe gaps a controlled car accepts when it changes lanes (its vType's
``lcAssertive``): an on-ramp car must leave its acceleration lane, and the gap it moves into is the
policy's to make, by its speed. With SUMO's own safe gaps (sized by the braking of the car behind) a
controlled ramp car ran to the end of its lane beside a wide gap. Left out on single-lane merges."""
CONTROLLED_TYPE = "agent"
ROBOT_TYPE = "robot"
# Controlled cars must not be clipped by their vType: the paper's hard brake is -4 m/s².
CONTROLLED_MAX_SPEED_MPS = 40.0
"""The controlled cars' top speed on a net whose limits are all at most this (the vType's ``maxSpeed``);
on a faster net it is the net's fastest limit (``controlled_top_speed``)."""
ROBOT_MAX_SPEED_MPS = 200.0 / 3.6
"""SUMO's default top speed of a passenger car, which the robot cars' vType keeps: no limit a car may
drive can be above it (``env/net_needs.py`` refuses such a net)."""
CONTROLLED_DECEL_MPS2 = 4.5
ROBOT_ACCEL_MPS2 = 2.0
ROBOT_DECEL_MPS2 = 2.0  # comfortable; a robot braking harder than HARD_BRAKE_DETECT counts as hard braking
VEHICLE_LENGTH_M = 5.0  # every car, controlled or not (the route file's vTypes)


def _swig() -> Any:
    """``libsumo._libsumo`` (libsumo's SWIG functions): ``import libsumo`` costs a dictionary lookup once
    loaded, where ``from libsumo import _libsumo`` inside a function goes through importlib every call
    (about 1 µs, twice a step)."""
    import libsumo

    return libsumo._libsumo


def load_libsumo() -> None:
    """Load libsumo's library now, if it is installed, starting no simulation: what a process that forks the
    workers running SUMO does once for them all (a fork of a process running a SUMO would not be safe)."""
    with contextlib.suppress(ImportError):
        _swig()


class RouteVehicle(Protocol):
    """What the route file needs of one vehicle (``env.scenario.VehicleSpec`` has it)."""

    @property
    def id(self) -> str: ...
    @property
    def road(self) -> str: ...  # 'main' or 'merge': the incoming road it starts on
    @property
    def depart_s(self) -> float: ...
    @property
    def start_pos_m(self) -> float: ...
    @property
    def speed_mps(self) -> float: ...
    @property
    def controlled(self) -> bool: ...


class RouteScenario(Protocol):
    """What SUMO needs of a scenario (``env.scenario.Scenario`` has it): sim knows no env types."""

    @property
    def vehicles(self) -> Sequence[RouteVehicle]: ...
    @property
    def controlled_ids(self) -> tuple[str, ...]: ...


class _SlotHolder(typing.Protocol):
    def close(self) -> None: ...


_active: _SlotHolder | None = None
"""The one libsumo simulation this process holds (a ``SumoBackend`` or a ``BatchBackend``)."""


def claim_slot(owner: _SlotHolder, what: str) -> None:
    """Refuse a second in-process simulation (libsumo would silently replace the first)."""
    if _active is not None and _active is not owner:
        raise SimulationError(
            "another SUMO simulation is already open in this process (libsumo allows one); " + what
        )


def hold_slot(owner: _SlotHolder | None) -> None:
    """Mark the slot held by ``owner`` (None: free)."""
    global _active
    _active = owner


def release_slot(owner: _SlotHolder) -> None:
    if _active is owner:
        hold_slot(None)


def end_run(owner: _SlotHolder, running: bool, workdir: Path | None) -> None:
    """What closing an in-process simulation takes, for either backend: ``libsumo.close`` when a run is
    open (errors ignored: the run may have died), the slot freed, the run's temp folder removed."""
    if running:
        import libsumo

        with contextlib.suppress(Exception):
            libsumo.close()
    release_slot(owner)
    if workdir is not None:
        shutil.rmtree(workdir, ignore_errors=True)


def start_or_load(args: Sequence[str], running: bool, net_path: object) -> None:
    """``libsumo.start`` (or ``load`` when a run is open) with SUMO's own reason on failure (bad input)."""
    import libsumo

    failure: BaseException | None = None
    with _captured_stderr() as stderr_lines:
        try:
            if running:
                libsumo.load(list(args[1:]))
            else:
                libsumo.start(list(args))
        except (libsumo.TraCIException, libsumo.FatalTraCIError) as err:
            failure = err
    if failure is not None:  # read SUMO's reason only now: the captured lines arrive on leaving the block
        raise SumoRefusedInput(f"SUMO could not load {net_path}: {_sumo_message(failure, stderr_lines)}")


def has_display() -> bool:
    """Whether sumo-gui can open a window here (without one it would abort the whole process)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def require_display(gui: bool) -> None:
    """Refuse ``--gui`` without a display (sumo-gui would abort the whole process)."""
    if gui and not has_display():
        raise InputError("--gui needs a display (DISPLAY is not set); run without --gui")


@contextlib.contextmanager
def _captured_stderr() -> Iterator[list[str]]:
    """Collect what libsumo prints on the C++ stderr (its only place for many error reasons)."""
    lines: list[str] = []
    saved = os.dup(2)
    try:
        with tempfile.TemporaryFile(mode="w+b") as sink:
            try:  # (a stop raised as soon as fd 2 is the sink must still put it back)
                os.dup2(sink.fileno(), 2)
                yield lines
            finally:
                os.dup2(saved, 2)
            sink.seek(0)
            lines.extend(sink.read().decode(errors="replace").splitlines())
    finally:
        os.close(saved)


def _sumo_message(err: BaseException, stderr_lines: Sequence[str]) -> str:
    errors = [ln.strip() for ln in stderr_lines if ln.strip().startswith("Error")]
    text = str(err).strip()
    if errors:
        return "; ".join(errors[-2:]) if not text or text == "Process Error" else f"{text} ({errors[-1]})"
    return text or type(err).__name__


def has_lane_changes(site: MergeSite) -> bool:
    """Whether a car on the routes through ``site`` could change lanes (an edge with several lanes):
    then every car gets ``LANE_KEEPING_MODE``."""
    sides: tuple[Side, ...] = ("main", "merge")
    return any(lane.lane_count > 1 for side in sides for lane in site.route(side))


def controlled_top_speed(site: MergeSite) -> float:
    """The controlled cars' vType top speed on ``site``: ``CONTROLLED_MAX_SPEED_MPS``, or the fastest
    limit on its routes where that is higher (SUMO refuses a departure above a vType's top speed and
    clips a commanded speed to it; the rule mask keeps the agents under each road's limit)."""
    return max(CONTROLLED_MAX_SPEED_MPS, site.fastest_limit_mps)


def _vtype_lines(lane_changes: bool = False, top_speed_mps: float = CONTROLLED_MAX_SPEED_MPS) -> list[str]:
    """The two vTypes, the controlled one with ``top_speed_mps`` (``controlled_top_speed``); with
    ``lane_changes`` (a multi-lane merge) the controlled cars' lane changes take any gap that is free
    (``CONTROLLED_LC_ASSERTIVE``)."""
    assertive = f' lcAssertive="{CONTROLLED_LC_ASSERTIVE:g}"' if lane_changes else ""
    return [
        f'  <vType id="{CONTROLLED_TYPE}" length="{VEHICLE_LENGTH_M}" minGap="2" accel="2" '
        f'decel="{CONTROLLED_DECEL_MPS2}" emergencyDecel="9" maxSpeed="{top_speed_mps}" sigma="0" '
        f'speedFactor="1" speedDev="0"{assertive} color="1,0,0"/>',
        f'  <vType id="{ROBOT_TYPE}" length="{VEHICLE_LENGTH_M}" minGap="2" accel="{ROBOT_ACCEL_MPS2}" '
        f'decel="{ROBOT_DECEL_MPS2}" emergencyDecel="9" sigma="0" tau="1.0" speedFactor="1" speedDev="0" '
        'color="0.6,0.6,0.6"/>',
    ]


def _route_lines(site: MergeSite, prefix: str = "") -> list[str]:
    """One route per approach, ``{prefix}main_route`` and ``{prefix}merge_route``: the approach's edges,
    then the road after the merge."""
    sides: tuple[Side, ...] = ("main", "merge")
    return [
        f'  <route id="{prefix}{side}_route" edges="{" ".join(site.route_edge_ids(side))}"/>'
        for side in sides
    ]


def _vehicle_lines(vehicles: Sequence[RouteVehicle], site: MergeSite, prefix: str = "") -> list[str]:
    """The vehicles sorted by (departure, id), ids prefixed. A car starts ``start_pos_m`` from the start
    of its approach's first lane counted along the approach's edges (``Approach.edge_point``: a
    junction-internal lane between two edges takes no room, so no car starts on one), on the
    approach's (controlled) lane of the edge holding that point: ``departEdge`` (its index in the
    route) when that is not the first edge, ``departLane`` when the edge has several lanes (SUMO's
    default is not the rightmost one). Both are left out otherwise: the generated T-junction's route
    file is what it was before merge sites. A start speed above the limit of the lane it starts on (an
    edge slower than its road's own, whose limit scales the drawn speeds) departs at that limit: SUMO
    refuses a departure above it."""
    lines = []
    for v in sorted(vehicles, key=lambda v: (v.depart_s, v.id)):
        vtype = CONTROLLED_TYPE if v.controlled else ROBOT_TYPE
        side: Side = "main" if v.road == "main" else "merge"
        approach = site.approach(side)
        first = approach.edges[0]
        if v.start_pos_m < first.length_m:
            lane, pos, edge_index = first, v.start_pos_m, 0  # the position as given, no round trip
        else:
            try:
                lane, pos = approach.edge_point(v.start_pos_m)
            except InputError as err:
                raise InputError(f"vehicle {v.id!r}: {err}") from None
            edge_index = site.route_edge_ids(side).index(lane.edge_id)
        where = (f' departEdge="{edge_index}"' if edge_index else "") + (
            f' departLane="{lane.lane_index}"' if lane.lane_count > 1 else ""
        )
        speed = min(v.speed_mps, math.floor(lane.speed_limit_mps * 1000.0) / 1000.0)  # as written: mm/s
        lines.append(
            f'  <vehicle id="{prefix}{v.id}" type="{vtype}" route="{prefix}{side}_route" depart="{v.depart_s:.2f}"'
            f'{where} departPos="{pos:.3f}" departSpeed="{speed:.3f}" insertionChecks="none"/>'
        )
    return lines


def _route_xml(scenario: RouteScenario, site: MergeSite) -> str:
    lines = [
        "<routes>",
        *_vtype_lines(has_lane_changes(site), controlled_top_speed(site)),
        *_route_lines(site),
        *_vehicle_lines(scenario.vehicles, site),
        "</routes>",
    ]
    return "\n".join(lines) + "\n"


def run_options(seed: int) -> list[str]:
    """SUMO's options of every run, the files aside (flag, value, flag, value, ...): also what an
    exported ``.sumocfg`` holds (sim/plain_sumo.py)."""
    return [
        "--step-length",
        str(STEP_LENGTH_S),
        "--seed",
        str(seed),
        "--collision.check-junctions",
        "true",
        "--collision.mingap-factor",
        "0",
        "--collision.action",
        "remove",
        "--time-to-teleport",
        "-1",
        "--no-step-log",
        "true",
        "--no-warnings",
        "true",
        "--default.speeddev",
        "0",
        "--begin",
        "0",
    ]


@dataclass(slots=True)  # (slots: built once per copy and step, about half the cost)
class StepEvents:
    """What happened in one simulation step."""

    collided: set[str] = field(default_factory=set)
    collision_pairs: list[tuple[str, str]] = field(default_factory=list)
    departed: list[str] = field(default_factory=list)
    arrived: list[str] = field(default_factory=list)
    """Left the network at the end of the outgoing road (removed-by-collision vehicles excluded)."""
    teleported: list[str] = field(default_factory=list)
    time_s: float = 0.0
    """Simulated time after the step."""


@dataclass(frozen=True)
class VehicleStates:
    """Raw per-vehicle state read from SUMO (arrays align with ids)."""

    ids: tuple[str, ...]
    edge: tuple[str, ...]
    lane_pos_m: np.ndarray
    speed_mps: np.ndarray
    accel_mps2: np.ndarray
    lane_index: np.ndarray | None = None
    """Each car's lane index on its edge, read only on a merge whose approaches share edges (a lane
    drop: ``MergeSite.shared_lanes``); None elsewhere."""


class SumoBackend:
    """The one SUMO simulation of this process."""

    def __init__(
        self,
        net: MergeSite | MergeNet,
        seed: int = 0,
        gui: bool = False,
        extra_args: Sequence[str] = (),
    ) -> None:
        self.site = as_site(net)
        """The merge the scenarios' cars drive through (a ``MergeNet`` is detected at its junction)."""
        self.seed = seed
        self.gui = gui
        self.extra_args = list(extra_args)
        self._workdir: Path | None = None
        self._running = False
        self._controlled: set[str] = set()
        self._released: set[str] = set()
        self._lane_keeping = has_lane_changes(self.site)
        self._read_lanes = bool(self.site.shared_lanes)

    # -- lifecycle -------------------------------------------------------------------------------
    def _args(self, route_file: Path) -> list[str]:
        binary = "sumo-gui" if self.gui else "sumo"
        return [
            binary,
            "--net-file",
            str(self.site.path),
            "--route-files",
            str(route_file),
            *run_options(self.seed),
            *self.extra_args,
        ]

    def reset(self, scenario: RouteScenario, extra_args: Sequence[str] = ()) -> None:
        """(Re)load the network with this scenario's vehicles (the insertion step is ``step``'s job).

        ``extra_args`` are SUMO options for this run only (e.g. ``--tripinfo-output FILE``).
        """
        claim_slot(
            self,
            "close the other environment first, or create it with make_backend() to run it in a subprocess",
        )
        require_display(self.gui)
        if self._workdir is None:
            self._workdir = Path(tempfile.mkdtemp(prefix="idas_sumo_"))
        route_file = self._workdir / "scenario.rou.xml"
        route_file.write_text(_route_xml(scenario, self.site))
        args = [*self._args(route_file), *extra_args]
        if self.gui:
            binary = "sumo-gui"
            from idas_sumo.sim.netgen import sumo_binary

            args[0] = str(sumo_binary(binary))
        try:
            start_or_load(args, self._running, self.site.path)
        except SumoRefusedInput:
            self._running = False
            hold_slot(None)
            raise
        self._running = True
        hold_slot(self)
        self._controlled = set(scenario.controlled_ids)
        self._released = set()

    def close(self) -> None:
        end_run(self, self._running, self._workdir)
        self._running = False
        self._workdir = None

    @property
    def running(self) -> bool:
        return self._running

    # -- stepping --------------------------------------------------------------------------------
    def time_s(self) -> float:
        import libsumo

        return float(libsumo.simulation.getTime())

    def set_speeds(self, speeds_mps: dict[str, float]) -> None:
        """Command the next step's speed of controlled vehicles (validated: finite, >= 0)."""
        self.set_speed_list(list(speeds_mps), list(speeds_mps.values()))

    def set_speed_list(self, vehicle_ids: Sequence[str], speeds_mps: Sequence[float]) -> None:
        """``set_speeds`` with the ids and their speeds as two lists (what the engine has at hand)."""
        import libsumo

        _libsumo = _swig()

        # A finite sum has no NaN or inf, and then the minimum is >= 0 (-0.0 too) exactly when every speed
        # is; only otherwise is each speed looked at, to name the bad one.
        if len(speeds_mps) != len(vehicle_ids) or (
            speeds_mps and not (math.isfinite(sum(speeds_mps)) and min(speeds_mps) >= 0)
        ):
            for vid, speed in zip(vehicle_ids, speeds_mps, strict=True):
                if not math.isfinite(speed) or speed < 0:
                    raise SimulationError(
                        f"invalid speed command {speed!r} for vehicle {vid!r} (a bug, not an input)"
                    )
        try:  # the common case in one pass, through libsumo's SWIG function (as BatchBackend does)
            deque(map(_libsumo.vehicle_setSpeed, vehicle_ids, speeds_mps), maxlen=0)
        except libsumo.TraCIException:
            # Some car is gone; setting a speed twice is harmless, so go again one by one.
            for vid, speed in zip(vehicle_ids, speeds_mps, strict=True):
                try:
                    _libsumo.vehicle_setSpeed(vid, speed)
                except libsumo.TraCIException as err:
                    if vid in libsumo.vehicle.getIDList():
                        raise SimulationError(f"SUMO refused the speed of vehicle {vid!r}: {err}") from None
                    # Removed by SUMO (or a tool) since the last step: the step reports it as 'removed'.

    def release(self, vehicle_id: str) -> None:
        """Hand a controlled vehicle back to SUMO's own driver model (after it finished)."""
        import libsumo

        if vehicle_id in self._controlled and vehicle_id not in self._released:
            libsumo.vehicle.setSpeedMode(vehicle_id, SUMO_DEFAULT_SPEED_MODE)
            libsumo.vehicle.setSpeed(vehicle_id, -1)
            self._released.add(vehicle_id)

    def remove(self, vehicle_id: str) -> None:
        """Take a vehicle off the road, as SUMO's ``--collision.action remove`` does (the engine's
        geometric collision check, env/engine.py); one already gone is no error."""
        import libsumo

        with contextlib.suppress(libsumo.TraCIException):
            libsumo.vehicle.remove(vehicle_id)

    def step(self) -> StepEvents:
        import libsumo

        _libsumo = _swig()  # (libsumo's module functions wrap these one call deeper each)
        try:
            # ``libsumo.simulationStep`` is this plus its step listeners, of which idas-sumo adds none.
            _libsumo.simulation_step(0.0)
        except (libsumo.TraCIException, libsumo.FatalTraCIError) as err:
            raise SimulationError(f"SUMO failed during a step: {err}") from None
        collided: set[str] = set()
        pairs: list[tuple[str, str]] = []
        for collision in libsumo.simulation.getCollisions():  # (through the module: tests silence it there)
            pairs.append((collision.collider, collision.victim))
            collided.update((collision.collider, collision.victim))
        departed = list(_libsumo.simulation_getDepartedIDList())
        arrived = _libsumo.simulation_getArrivedIDList()
        for vid in departed:
            if vid in self._controlled:
                libsumo.vehicle.setSpeedMode(vid, CONTROLLED_SPEED_MODE)
            if self._lane_keeping:
                libsumo.vehicle.setLaneChangeMode(vid, LANE_KEEPING_MODE)
        return StepEvents(
            collided,
            pairs,
            departed,
            [v for v in arrived if v not in collided] if collided else list(arrived),
            list(_libsumo.simulation_getStartingTeleportIDList()),
            float(_libsumo.simulation_getTime()),
        )

    def vehicle_states(self) -> VehicleStates:
        """Every vehicle's edge, lane position, speed and acceleration: the plain getters through libsumo's
        SWIG functions, ``map`` into ``np.fromiter`` (``BatchBackend.vehicle_states``' reader)."""
        _libsumo = _swig()

        ids = _libsumo.vehicle_getIDList()
        n = len(ids)
        edges = tuple(map(_libsumo.vehicle_getRoadID, ids))
        lane_pos = np.fromiter(map(_libsumo.vehicle_getLanePosition, ids), np.float64, n)
        speed = np.fromiter(map(_libsumo.vehicle_getSpeed, ids), np.float64, n)
        accel = np.fromiter(map(_libsumo.vehicle_getAcceleration, ids), np.float64, n)
        lane_index = None
        if self._read_lanes:
            lane_index = np.fromiter(map(_libsumo.vehicle_getLaneIndex, ids), np.int64, n)
        return built(  # (``VehicleStates(...)``, every field given)
            VehicleStates,
            ids=tuple(ids),
            edge=edges,
            lane_pos_m=lane_pos,
            speed_mps=speed,
            accel_mps2=accel,
            lane_index=lane_index,
        )

    def raw_call(self, domain: str, method: str, *args: Any) -> Any:
        """Escape hatch for tests and tools: call libsumo.<domain>.<method>(*args)."""
        import libsumo

        return getattr(getattr(libsumo, domain), method)(*args)


@atexit.register
def _close_on_exit() -> None:
    if _active is not None:
        _active.close()


def slot_taken() -> bool:
    """True while an in-process SUMO simulation is open."""
    return _active is not None


# -- a second simulation: SUMO in a child process --------------------------------------------------
#
# The child is started, and calls back on an authenticated loopback socket, through sim/rpc.py (see
# there why not multiprocessing, and how the key travels); it then serves ``serve_backend``.

_CHILD_START_TIMEOUT_S = 60.0
_CHILD_CLOSE_TIMEOUT_S = 5.0


def _portable_error(err: Exception) -> Exception:
    """``err`` if it survives pickling (to be re-raised in the parent as is), else a SimulationError."""
    import pickle

    try:
        pickle.loads(pickle.dumps(err))
    except Exception:
        return SimulationError(f"{type(err).__name__} in the SUMO subprocess: {err}")
    return err


def serve_backend(conn: Any) -> None:
    """Child side of ``SubprocessBackend`` (the child's entry): run calls on a local backend until
    told to close."""
    import pickle

    backend: SumoBackend | None = None
    try:
        while True:
            try:
                method, args = conn.recv()
            except Exception:  # the parent is gone, or was interrupted mid-message: nobody to answer
                return
            if method == "close":
                conn.send(("ok", None))
                return
            try:
                if method == "open":
                    backend = SumoBackend(*args)
                    result = None
                else:
                    assert backend is not None, "'open' comes first"
                    result = getattr(backend, method)(*args)
            except Exception as err:  # sent back and re-raised in the parent
                conn.send(("error", _portable_error(err)))
                continue
            try:  # send() pickles before it writes: a result that cannot travel leaves the channel intact
                conn.send(("ok", result))
            except (pickle.PicklingError, TypeError, AttributeError) as err:
                conn.send(
                    ("error", SimulationError(f"the result of {method} cannot leave the subprocess: {err}"))
                )
    except OSError:  # the parent went away while we answered
        pass
    finally:
        if backend is not None:
            backend.close()


def _stop_child(proc: Any, conn: Any) -> None:
    """Ask the child to close SUMO and exit; kill it when it does not within the timeout (stuck)."""
    import subprocess

    with contextlib.suppress(Exception):
        conn.send(("close", ()))
        conn.poll(_CHILD_CLOSE_TIMEOUT_S)
    with contextlib.suppress(Exception):
        conn.close()
    try:
        proc.wait(timeout=_CHILD_CLOSE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class SubprocessBackend:
    """The same interface as ``SumoBackend``, with SUMO in a child process (for a second simulation)."""

    def __init__(self, net: MergeSite | MergeNet, seed: int = 0, gui: bool = False) -> None:
        import weakref

        self.site = as_site(net)
        self._closed = False
        self._proc, self._conn = self._start_child()
        # Closes the child when this object is collected or the interpreter exits without close().
        self._finalizer = weakref.finalize(self, _stop_child, self._proc, self._conn)
        try:
            self._call("open", self.site, seed, gui)
        except BaseException:
            self.close()
            raise

    def _start_child(self) -> tuple[Any, Any]:
        """The child process, and its authenticated connection once it called back."""
        with CallBackServer() as server:
            proc = server.launch("idas_sumo.sim.backend:serve_backend")
            try:
                conn = server.accept([proc], time.monotonic() + _CHILD_START_TIMEOUT_S)
            except BaseException as err:  # a Ctrl-C included: leave no child behind
                proc.kill()
                proc.wait()
                if not isinstance(err, NoCallBack):
                    raise
                if err.exited:
                    raise SimulationError(f"the SUMO subprocess died (exit code {proc.returncode})") from None
                raise SimulationError("the SUMO subprocess did not start within a minute") from None
        return proc, conn

    def _died(self) -> SimulationError:
        import subprocess

        with contextlib.suppress(subprocess.TimeoutExpired):
            self._proc.wait(timeout=_CHILD_CLOSE_TIMEOUT_S)  # the channel breaks just before the exit
        return SimulationError(f"the SUMO subprocess died (exit code {self._proc.returncode})")

    def _call(self, method: str, *args: Any) -> Any:
        if self._closed:
            raise SimulationError("this SUMO simulation is closed")
        try:
            self._conn.send((method, args))
            while not self._conn.poll(1.0):
                if self._proc.poll() is not None:
                    raise self._died()
            status, value = self._conn.recv()
        except (EOFError, OSError):
            raise self._died() from None
        except KeyboardInterrupt:  # the channel may hold half a message now: this simulation is over
            self.close()
            raise
        if status == "error":
            raise value
        return value

    def reset(self, scenario: RouteScenario, extra_args: Sequence[str] = ()) -> None:
        self._call("reset", scenario, list(extra_args))

    def step(self) -> StepEvents:
        return typing.cast(StepEvents, self._call("step"))

    def set_speeds(self, speeds_mps: dict[str, float]) -> None:
        self._call("set_speeds", speeds_mps)

    def set_speed_list(self, vehicle_ids: Sequence[str], speeds_mps: Sequence[float]) -> None:
        self._call("set_speed_list", list(vehicle_ids), list(speeds_mps))

    def release(self, vehicle_id: str) -> None:
        self._call("release", vehicle_id)

    def remove(self, vehicle_id: str) -> None:
        self._call("remove", vehicle_id)

    def vehicle_states(self) -> VehicleStates:
        return typing.cast(VehicleStates, self._call("vehicle_states"))

    def time_s(self) -> float:
        return typing.cast(float, self._call("time_s"))

    def raw_call(self, domain: str, method: str, *args: Any) -> Any:
        return self._call("raw_call", domain, method, *args)

    def close(self) -> None:
        """Close SUMO and end the child (killed if it does not answer); a second call does nothing."""
        self._closed = True
        self._finalizer()


Backend = SumoBackend | SubprocessBackend


def make_backend(net: MergeSite | MergeNet, seed: int = 0, gui: bool = False) -> Backend:
    """In-process SUMO when this process has none open yet, else SUMO in a subprocess."""
    if slot_taken():
        return SubprocessBackend(net, seed=seed, gui=gui)
    return SumoBackend(net, seed=seed, gui=gui)
