"""Traffic as SUMO flows through a merge, and the one libsumo run of a co-simulation (``idas-sumo cosim``).

SUMO inserts the cars (``<flow>``, vehicles per hour per incoming road, its own insertion checks). A
share ``p`` of them is *automated*: their vType is drawn per car from a ``vTypeDistribution`` by SUMO's
own random number generator (``--seed``), and the co-simulation drives them; the others keep SUMO's
car-following and lane-change models with their usual driver imperfection (``sigma``, speed factors).
With p = 0 the demand file holds the human vType and the flows only, and the run's loop commands
nothing: it is plain SUMO (``tests/test_cosim.py`` runs the ``sumo`` binary on the same files).

Every input and output of one run is named in one ``.sumocfg`` (``write_run_files``), so the same run
can be started through libsumo (``FlowSimulation``) or the ``sumo`` binary (``run_plain_sumo``). SUMO
measures the flow statistics itself: tripinfo (travel time, time loss, depart delay per car), induction
loops on every lane just past the merge point (throughput), edge data per time bin (speed, distance)
its summary (the insertion backlog), statistics (collisions, teleports) and collision output (who hit whom).
"""

from __future__ import annotations

import math
import subprocess
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from idas_sumo.errors import SimulationError
from idas_sumo.sim.backend import (
    CONTROLLED_DECEL_MPS2,
    CONTROLLED_LC_ASSERTIVE,
    CONTROLLED_SPEED_MODE,
    LANE_KEEPING_MODE,
    STEP_LENGTH_S,
    SUMO_DEFAULT_SPEED_MODE,
    VEHICLE_LENGTH_M,
    claim_slot,
    controlled_top_speed,
    end_run,
    has_lane_changes,
    hold_slot,
    start_or_load,
)
from idas_sumo.sim.merge_detect import MergeSite, Side
from idas_sumo.sim.netgen import sumo_binary

HUMAN_TYPE = "human"
"""SUMO-driven cars: SUMO's default passenger car (Krauss, sigma 0.5, speed factors around 1), 5 m long."""
AUTOMATED_TYPE = "automated"
"""Cars the co-simulation drives (the engine's controlled vType: no SUMO limit on the paper's actions)."""
MIXED_TYPE = "mixed"
"""The vTypeDistribution a flow draws each car's type from when 0 < p < 1."""
SIDES: tuple[Side, ...] = ("main", "merge")
CONFIG_NAME = "run.sumocfg"
ROUTE_NAME = "demand.rou.xml"
ADDITIONAL_NAME = "measure.add.xml"
OUTPUT_NAMES = {
    "tripinfo": "tripinfo.xml",
    "statistic": "statistics.xml",
    "summary": "summary.xml",
    "loops": "loops.xml",
    "edgedata": "edgedata.xml",
    "collisions": "collisions.xml",
}
"""What SUMO writes in a run's folder (the additional file's outputs are relative to it, as are the config's)."""
LOOP_POS_M = 1.0
"""The throughput loops' position on each lane of the road after the merge point (m from its start)."""


@dataclass(frozen=True)
class FlowDemand:
    """One run's traffic: vehicles per hour entering each incoming road, a share automated, for a time."""

    veh_per_h: Mapping[Side, float]
    """Per approach ('main', 'merge'); 0 (or absent): no flow on that road."""
    penetration: float
    """The probability that an inserted car is automated, in [0, 1]."""
    duration_s: float
    """Simulated seconds; cars are inserted until then."""
    seed: int
    """SUMO's ``--seed``: its driver imperfection, and each car's draw of automated or not."""
    bin_s: float
    """The statistics' time bin (detector and edge data period)."""
    profile: tuple[tuple[float, float], ...] = ()
    """A time profile of the demand: (start s, multiplier) steps, the first at 0, each multiplying
    ``veh_per_h`` until the next starts (empty: the demand is constant)."""

    def intervals(self) -> list[tuple[float, float, float]]:
        """(begin s, end s, multiplier) of each step of the profile inside the run ((0, duration, 1)
        without one)."""
        steps = self.profile or ((0.0, 1.0),)
        ends = [t for t, _ in steps[1:]] + [self.duration_s]
        return [
            (t, min(end, self.duration_s), m)
            for (t, m), end in zip(steps, ends, strict=True)
            if t < self.duration_s
        ]


def _vtypes(site: MergeSite, penetration: float) -> list[str]:
    human = f'  <vType id="{HUMAN_TYPE}" length="{VEHICLE_LENGTH_M}" color="0.6,0.6,0.6"'
    assertive = f' lcAssertive="{CONTROLLED_LC_ASSERTIVE:g}"' if has_lane_changes(site) else ""
    automated = (
        f'  <vType id="{AUTOMATED_TYPE}" length="{VEHICLE_LENGTH_M}" minGap="2" accel="2" '
        f'decel="{CONTROLLED_DECEL_MPS2}" emergencyDecel="9" maxSpeed="{controlled_top_speed(site)}" '
        f'sigma="0" speedFactor="1" speedDev="0"{assertive} color="1,0,0"'
    )
    if penetration <= 0.0:
        return [human + "/>"]
    if penetration >= 1.0:
        return [automated + "/>"]
    return [
        f'  <vTypeDistribution id="{MIXED_TYPE}">',
        "  " + human + f' probability="{1.0 - penetration!r}"/>',
        "  " + automated + f' probability="{penetration!r}"/>',
        "  </vTypeDistribution>",
    ]


def flow_type(penetration: float) -> str:
    """The vType (or distribution) every flow's cars take at this penetration rate."""
    if penetration <= 0.0:
        return HUMAN_TYPE
    return AUTOMATED_TYPE if penetration >= 1.0 else MIXED_TYPE


def demand_xml(site: MergeSite, demand: FlowDemand) -> str:
    """The route file: the vTypes, one route per approach (its edges, then the road after the merge) and
    one ``<flow>`` per road with traffic, named after the road (SUMO names its cars ``main.0``, ...)."""
    lines = ["<routes>", *_vtypes(site, demand.penetration)]
    for side in SIDES:
        lines.append(f'  <route id="{side}_route" edges="{" ".join(site.route_edge_ids(side))}"/>')
    vtype = flow_type(demand.penetration)
    steps = demand.intervals()
    for side in SIDES:
        rate = float(demand.veh_per_h.get(side, 0.0))
        for i, (begin, end, multiplier) in enumerate(steps):
            if rate * multiplier <= 0.0:
                continue
            # one flow per step of a profile, named SIDE.I (its cars SIDE.I.N: the road is the first part)
            name = f"{side}.{i}" if demand.profile else side
            lines.append(
                f'  <flow id="{name}" type="{vtype}" route="{side}_route" begin="{begin:g}" '
                f'end="{end:g}" vehsPerHour="{rate * multiplier!r}" departLane="best" departSpeed="max"/>'
            )
    lines.append("</routes>")
    return "\n".join(lines) + "\n"


def out_lane_ids(site: MergeSite) -> list[str]:
    """Every lane of the first road after the merge point (the throughput loops' lanes)."""
    first = site.out[0]
    return [f"{first.edge_id}_{i}" for i in range(first.lane_count)]


def measure_xml(site: MergeSite, demand: FlowDemand) -> str:
    """The additional file: an induction loop on every lane just past the merge point, and edge data."""
    first = site.out[0]
    pos = min(LOOP_POS_M, first.length_m / 2.0)
    period = f"{demand.bin_s:g}"
    lines = ["<additional>"]
    for lane in out_lane_ids(site):
        lines.append(
            f'  <inductionLoop id="past_merge_{lane}" lane="{lane}" pos="{pos:g}" period="{period}" '
            f'file="{OUTPUT_NAMES["loops"]}"/>'
        )
    lines.append(f'  <edgeData id="bins" period="{period}" file="{OUTPUT_NAMES["edgedata"]}"/>')
    lines.append("</additional>")
    return "\n".join(lines) + "\n"


def config_xml(site: MergeSite, demand: FlowDemand) -> str:
    """The ``.sumocfg`` naming the net, the demand, the measurements and the run's options; every output
    is relative to the config's folder. Collisions as the engine has them (any overlap, in junctions too,
    the cars removed); SUMO's own teleporting of stuck cars stays on (a teleport is a statistic here)."""
    options = {
        "net-file": str(site.path.resolve()),
        "route-files": ROUTE_NAME,
        "additional-files": ADDITIONAL_NAME,
        "begin": "0",
        "end": f"{demand.duration_s:g}",
        "step-length": f"{STEP_LENGTH_S:g}",
        "seed": str(demand.seed),
        "collision.check-junctions": "true",
        "collision.mingap-factor": "0",
        "collision.action": "remove",
        "tripinfo-output": OUTPUT_NAMES["tripinfo"],
        "tripinfo-output.write-unfinished": "true",
        "statistic-output": OUTPUT_NAMES["statistic"],
        "collision-output": OUTPUT_NAMES["collisions"],
        "summary-output": OUTPUT_NAMES["summary"],
        "summary-output.period": f"{demand.bin_s:g}",
        "no-step-log": "true",
        "no-warnings": "true",
        "duration-log.disable": "true",
    }
    body = "\n".join(f"    <{k} value={quoteattr(v)}/>" for k, v in options.items())
    return f"<configuration>\n  <input>\n{body}\n  </input>\n</configuration>\n"


def write_run_files(site: MergeSite, demand: FlowDemand, folder: Path) -> Path:
    """Write the run's config, demand and measurement files into ``folder``; the config's path."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / ROUTE_NAME).write_text(demand_xml(site, demand))
    (folder / ADDITIONAL_NAME).write_text(measure_xml(site, demand))
    config = folder / CONFIG_NAME
    config.write_text(config_xml(site, demand))
    return config


def run_plain_sumo(config: Path, timeout_s: float | None = None) -> None:
    """Run the ``sumo`` binary on a run's config (plain SUMO, no idas-sumo in the loop)."""
    proc = subprocess.run(
        [str(sumo_binary("sumo")), "-c", str(config)],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )
    if proc.returncode != 0:
        raise SimulationError(f"sumo -c {config} failed: {proc.stderr.strip()[-500:]}")


@dataclass
class FlowStep:
    """What one step of a flow simulation did."""

    time_s: float
    departed: list[str] = field(default_factory=list)
    automated_departed: list[str] = field(default_factory=list)
    collision_pairs: list[tuple[str, str]] = field(default_factory=list)
    teleported: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class FlowStates:
    """Every car on the road after a step (arrays align with ``ids``)."""

    ids: tuple[str, ...]
    edge: tuple[str, ...]
    lane_pos_m: np.ndarray
    speed_mps: np.ndarray
    accel_mps2: np.ndarray
    lane_index: np.ndarray | None
    """Read only on a merge with multi-lane edges (None elsewhere: every car is on the merge's lanes)."""


class FlowSimulation:
    """The one libsumo simulation of a co-simulation run: SUMO inserts and drives every car; the run's
    loop takes automated cars (their vType) over (``take``) and commands their speeds. Nothing else is
    commanded."""

    def __init__(self, site: MergeSite, config: Path) -> None:
        self.site = site
        self.config = config
        self._running = False
        self._lane_keeping = has_lane_changes(site)
        self._read_lanes = self._lane_keeping or bool(site.shared_lanes)

    def start(self) -> None:
        claim_slot(self, "close the other environment first (a co-simulation runs SUMO in this process)")
        start_or_load(["sumo", "-c", str(self.config)], False, self.site.path)
        self._running = True
        hold_slot(self)

    def step(self) -> FlowStep:
        import libsumo

        try:
            libsumo.simulationStep()
        except (libsumo.TraCIException, libsumo.FatalTraCIError) as err:
            raise SimulationError(f"SUMO failed during a step: {err}") from None
        step = FlowStep(time_s=float(libsumo.simulation.getTime()))
        step.collision_pairs = [(c.collider, c.victim) for c in libsumo.simulation.getCollisions()]
        step.teleported = list(libsumo.simulation.getStartingTeleportIDList())
        step.departed = list(libsumo.simulation.getDepartedIDList())
        get_type = libsumo.vehicle.getTypeID
        step.automated_departed = [v for v in step.departed if get_type(v) == AUTOMATED_TYPE]
        return step

    def take(self, vehicle_id: str) -> None:
        """An automated car comes under the co-simulation's control: every SUMO check of its speed off
        (the engine's speed mode), and on a multi-lane merge the engine's lane-keeping mode."""
        import libsumo

        libsumo.vehicle.setSpeedMode(vehicle_id, CONTROLLED_SPEED_MODE)
        if self._lane_keeping:
            libsumo.vehicle.setLaneChangeMode(vehicle_id, LANE_KEEPING_MODE)

    def states(self) -> FlowStates:
        import libsumo

        vehicle = libsumo.vehicle
        ids = tuple(vehicle.getIDList())
        n = len(ids)
        lane_index = np.fromiter(map(vehicle.getLaneIndex, ids), np.int64, n) if self._read_lanes else None
        return FlowStates(
            ids=ids,
            edge=tuple(map(vehicle.getRoadID, ids)),
            lane_pos_m=np.fromiter(map(vehicle.getLanePosition, ids), np.float64, n),
            speed_mps=np.fromiter(map(vehicle.getSpeed, ids), np.float64, n),
            accel_mps2=np.fromiter(map(vehicle.getAcceleration, ids), np.float64, n),
            lane_index=lane_index,
        )

    def set_speeds(self, ids: Sequence[str], speeds_mps: np.ndarray) -> None:
        """Command the next step's speed of automated cars (finite, >= 0: anything else is a bug)."""
        import libsumo

        for vid, speed in zip(ids, speeds_mps.tolist(), strict=True):
            if not math.isfinite(speed) or speed < 0:
                raise SimulationError(f"invalid speed command {speed!r} for vehicle {vid!r} (a bug)")
            libsumo.vehicle.setSpeed(vid, speed)

    def release(self, vehicle_id: str) -> None:
        """Hand an automated car back to SUMO's own model (it passed the merge)."""
        import libsumo

        libsumo.vehicle.setSpeedMode(vehicle_id, SUMO_DEFAULT_SPEED_MODE)
        libsumo.vehicle.setSpeed(vehicle_id, -1)

    def remove(self, vehicle_id: str) -> None:
        """Take a car off the road, as ``--collision.action remove`` does (a collision SUMO missed)."""
        import libsumo

        if vehicle_id in libsumo.vehicle.getIDList():
            libsumo.vehicle.remove(vehicle_id)

    def pending(self) -> int:
        """Cars due to depart that SUMO could not insert yet (the insertion backlog)."""
        import libsumo

        return len(libsumo.simulation.getPendingVehicles())

    def close(self) -> None:
        """End the run: SUMO writes its outputs (tripinfo, statistics) as it closes."""
        end_run(self, self._running, None)
        self._running = False


__all__ = [
    "AUTOMATED_TYPE",
    "HUMAN_TYPE",
    "OUTPUT_NAMES",
    "FlowDemand",
    "FlowSimulation",
    "FlowStates",
    "FlowStep",
    "demand_xml",
    "flow_type",
    "measure_xml",
    "out_lane_ids",
    "run_plain_sumo",
    "write_run_files",
]
