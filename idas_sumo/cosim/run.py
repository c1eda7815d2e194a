"""One co-simulation run: SUMO inserts the demand, the adapter drives the automated cars, SUMO measures.

The loop steps libsumo for the run's duration. Each step it hands the automated cars that departed to
the adapter (cosim/control.py), reads every car on the road, and applies the adapter's speeds, releases
and removals; SUMO-driven cars are never commanded. With no automated car the loop only reads: the run
is plain SUMO on the same files (``tests/test_cosim.py`` checks it against the ``sumo`` binary).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from idas_sumo import stops
from idas_sumo.cosim.control import AutomatedDriver
from idas_sumo.cosim.stats import EngineCounts, Row, bin_rows, run_row
from idas_sumo.env.actions import DEFAULT_SAFETY_MASK, SafetyMask
from idas_sumo.env.contracts import Policy
from idas_sumo.env.snapshot import MAIN, MERGE, OUT
from idas_sumo.sim.backend import STEP_LENGTH_S
from idas_sumo.sim.flows import FlowDemand, FlowSimulation, write_run_files
from idas_sumo.sim.merge_detect import MergeSite


@dataclass(frozen=True)
class RunResult:
    row: Row
    """The run's statistics (``stats.run_row``) and its speed."""
    bins: list[Row]
    trajectory: list[tuple[float, str, str, float, float, int]] | None = None
    """With ``trajectories``: (time s, car, road, position m past the merge point, speed m/s, automated
    0/1) of every car on the merge's lanes, each whole second."""


def _bin(time_s: float, bin_s: float, bins: int) -> int:
    """The bin of the step that ended at ``time_s``."""
    return min(int((time_s - STEP_LENGTH_S / 2) // bin_s), bins - 1)


ROAD_NAMES = {MAIN: "main", MERGE: "merge", OUT: "out"}
TRAJECTORY_PERIOD_S = 1.0


def _sample(
    driver: AutomatedDriver,
    time_s: float,
    automated: set[str],
    into: list[tuple[float, str, str, float, float, int]],
) -> None:
    """The trajectory rows of this step (each whole second): the cars in the driver's snapshot."""
    snap = driver.snapshot
    ticks = time_s / TRAJECTORY_PERIOD_S
    if snap is None or abs(ticks - round(ticks)) > 1e-6:
        return
    t = round(time_s, 3)
    for vid, road, dist, speed in zip(
        snap.ids, snap.road.tolist(), snap.dist_to_merge_m.tolist(), snap.speed_mps.tolist(), strict=True
    ):
        into.append((t, vid, ROAD_NAMES[road], round(-dist, 2), round(speed, 2), int(vid in automated)))


def simulate(
    site: MergeSite,
    demand: FlowDemand,
    policy: Policy | None,
    folder: Path,
    safety_mask: SafetyMask = DEFAULT_SAFETY_MASK,
    trajectory: list[tuple[float, str, str, float, float, int]] | None = None,
) -> EngineCounts:
    """Run ``demand`` through ``site`` with SUMO's outputs in ``folder``; the loop's own counts.
    ``policy`` drives the automated cars (None only where there are none: p = 0). ``trajectory``: a
    list the run appends each second's positions to (``RunResult.trajectory``)."""
    automated: set[str] = set()
    if policy is None and demand.penetration > 0:
        raise ValueError("automated cars need a policy")
    bins = round(demand.duration_s / demand.bin_s)
    counts = EngineCounts(bins)
    sim = FlowSimulation(site, write_run_files(site, demand, folder))
    driver = AutomatedDriver(site, policy, safety_mask)
    steps = round(demand.duration_s / STEP_LENGTH_S)
    sim.start()
    try:
        for _ in range(steps):
            stops.check()
            ev = sim.step()
            b = _bin(ev.time_s, demand.bin_s, bins)
            counts.sumo_collisions[b] += len(ev.collision_pairs)
            counts.teleports[b] += len(ev.teleported)
            driver.take(ev.automated_departed)
            commands, step = driver.step(sim.states(), ev.time_s)
            if trajectory is not None:
                automated.update(ev.automated_departed)
                _sample(driver, ev.time_s, automated, trajectory)
            counts.hard_brakes[b] += step.hard_brakes
            counts.crossed[b] += step.crossed
            counts.geometric_collisions[b] += step.geometric_collisions
            for vid in commands.take:
                sim.take(vid)
            for vid in commands.remove:
                sim.remove(vid)
            for vid in commands.release:
                sim.release(vid)
            if commands.ids:
                sim.set_speeds(commands.ids, commands.speeds_mps)
    finally:
        sim.close()
    return counts


def run_once(
    site: MergeSite,
    demand: FlowDemand,
    policy: Policy | None,
    folder: Path,
    safety_mask: SafetyMask = DEFAULT_SAFETY_MASK,
    warmup_s: float = 0.0,
    trajectories: bool = False,
) -> RunResult:
    """``simulate``, then the run's statistics after ``warmup_s`` (``stats.run_row``); ``row`` adds its
    wall time and real-time factor. ``trajectories``: record the positions too (slower, larger)."""
    trajectory: list[tuple[float, str, str, float, float, int]] | None = [] if trajectories else None
    start = time.perf_counter()
    counts = simulate(site, demand, policy, folder, safety_mask, trajectory)
    wall_s = time.perf_counter() - start
    row = run_row(folder, counts, demand.duration_s, warmup_s)
    row["wall_s"] = wall_s
    row["real_time_factor"] = demand.duration_s / wall_s if wall_s > 0 else float("inf")
    return RunResult(row=row, bins=bin_rows(folder, counts, demand.bin_s), trajectory=trajectory)


__all__ = ["RunResult", "run_once", "simulate"]
