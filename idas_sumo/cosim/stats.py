"""Flow statistics of one co-simulation run, per run and per time bin, as SUMO measured them.

SUMO's outputs (sim/flows.py names them) give: throughput past the merge point (the induction loops on
every lane just after it), travel time, time loss and depart delay per car (tripinfo; a trip counts in
the bin it arrived in, cars still on the road at the end in no travel time), mean speed and vehicle-km
(edge data: distance over time spent, on every edge), collisions and teleports (statistics) and the
insertion backlog (summary: cars due to depart that SUMO could not insert yet, at each bin's end).
The run's own loop adds what SUMO does not count: hard brakes (a car starting to brake at
``HARD_BRAKE_DETECT_MPS2`` or harder), collisions it found that SUMO missed, and its own count of cars
past the merge point (``engine_throughput_veh_per_h``, a cross-check of the loops).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from idas_sumo.sim.flows import AUTOMATED_TYPE, OUTPUT_NAMES, SIDES

Row = dict[str, Any]
TRIP_COLUMNS = ("travel_time_s", "time_loss_s")


@dataclass
class EngineCounts:
    """The run loop's own counts, per time bin."""

    bins: int
    hard_brakes: list[int] = field(default_factory=list)
    crossed: list[int] = field(default_factory=list)
    sumo_collisions: list[int] = field(default_factory=list)
    geometric_collisions: list[int] = field(default_factory=list)
    teleports: list[int] = field(default_factory=list)

    def __post_init__(self) -> None:
        for name in ("hard_brakes", "crossed", "sumo_collisions", "geometric_collisions", "teleports"):
            setattr(self, name, [0] * self.bins)


@dataclass(frozen=True)
class Trip:
    road: str
    automated: bool
    depart_s: float
    depart_delay_s: float
    arrival_s: float
    """-1: still on the road when the run ended, or removed (collided)."""
    travel_time_s: float
    time_loss_s: float


def _elements(path: Path, tag: str) -> Iterable[ET.Element]:
    for _, elem in ET.iterparse(path, events=("end",)):
        if elem.tag == tag:
            yield elem


def read_trips(folder: Path) -> list[Trip]:
    """Every car SUMO inserted (tripinfo, unfinished ones included)."""
    trips = []
    for e in _elements(folder / OUTPUT_NAMES["tripinfo"], "tripinfo"):
        done = e.get("vaporized", "") == "" and float(e.get("arrival", "-1")) >= 0
        trips.append(
            Trip(
                road=str(e.get("id", "")).partition(".")[0],
                automated=e.get("vType") == AUTOMATED_TYPE,
                depart_s=float(e.get("depart", "-1")),
                depart_delay_s=float(e.get("departDelay", "0")),
                arrival_s=float(e.get("arrival", "-1")) if done else -1.0,
                travel_time_s=float(e.get("duration", "nan")),
                time_loss_s=float(e.get("timeLoss", "nan")),
            )
        )
    return trips


def _bin_of(begin_s: float, bin_s: float) -> int:
    return round(begin_s / bin_s)


def read_loops(folder: Path, bin_s: float, bins: int) -> list[int]:
    """Cars past the merge point per bin (all lanes' loops summed)."""
    counts = [0] * bins
    for e in _elements(folder / OUTPUT_NAMES["loops"], "interval"):
        b = _bin_of(float(e.get("begin", "0")), bin_s)
        if b < bins:
            counts[b] += int(e.get("nVehContrib", "0"))
    return counts


def read_edgedata(folder: Path, bin_s: float, bins: int) -> tuple[list[float], list[float]]:
    """(metres driven, seconds driven) per bin, over every edge."""
    dist, time = [0.0] * bins, [0.0] * bins
    for interval in _elements(folder / OUTPUT_NAMES["edgedata"], "interval"):
        b = _bin_of(float(interval.get("begin", "0")), bin_s)
        if b >= bins:
            continue
        for edge in interval.iter("edge"):
            seconds = float(edge.get("sampledSeconds", "0"))
            time[b] += seconds
            dist[b] += float(edge.get("speed", "0")) * seconds
    return dist, time


def read_backlog(folder: Path, bin_s: float, bins: int) -> list[int]:
    """Cars waiting to be inserted at the end of each bin (summary at the bin boundaries; the last from
    the statistics, written at the end of the run)."""
    backlog = [0] * bins
    for e in _elements(folder / OUTPUT_NAMES["summary"], "step"):
        b = _bin_of(float(e.get("time", "0")), bin_s) - 1
        if 0 <= b < bins:
            backlog[b] = int(e.get("waiting", "0"))
    vehicles = read_statistics(folder)
    backlog[-1] = vehicles["waiting"]
    return backlog


def read_statistics(folder: Path) -> dict[str, int]:
    """SUMO's run statistics: loaded, inserted, running, waiting, collisions, teleports."""
    root = ET.parse(folder / OUTPUT_NAMES["statistic"]).getroot()
    vehicles = root.find("vehicles")
    teleports = root.find("teleports")
    safety = root.find("safety")
    out = {
        k: int((vehicles.get(k) if vehicles is not None else None) or 0)
        for k in ("loaded", "inserted", "running", "waiting")
    }
    out["teleports"] = int((teleports.get("total") if teleports is not None else None) or 0)
    out["collisions"] = int((safety.get("collisions") if safety is not None else None) or 0)
    return out


def read_collisions(folder: Path) -> list[tuple[float, int]]:
    """Each collision SUMO saw: (time s, how many of its two cars were automated)."""
    return [
        (
            float(e.get("time", "0")),
            (e.get("colliderType") == AUTOMATED_TYPE) + (e.get("victimType") == AUTOMATED_TYPE),
        )
        for e in _elements(folder / OUTPUT_NAMES["collisions"], "collision")
    ]


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else math.nan


def _p95(values: list[float]) -> float:
    return float(np.percentile(values, 95)) if values else math.nan


def trip_columns(trips: list[Trip], prefix: str = "") -> Row:
    """Mean and 95th percentile of travel time and time loss over finished trips, overall and per road."""
    row: Row = {}
    groups = [("", trips)] + [(f"{side}_", [t for t in trips if t.road == side]) for side in SIDES]
    for name, group in groups:
        for col in TRIP_COLUMNS:
            values = [getattr(t, col) for t in group if t.arrival_s >= 0]
            row[f"{prefix}{name}mean_{col}"] = _mean(values)
            row[f"{prefix}{name}p95_{col}"] = _p95(values)
    return row


def _per_1000_km(count: int, metres: float) -> float:
    return count / (metres / 1e6) if metres > 0 else math.nan


def bin_rows(folder: Path, counts: EngineCounts, bin_s: float) -> list[Row]:
    """One row per time bin."""
    bins = counts.bins
    loops = read_loops(folder, bin_s, bins)
    dist, time = read_edgedata(folder, bin_s, bins)
    backlog = read_backlog(folder, bin_s, bins)
    trips = read_trips(folder)
    rows = []
    for b in range(bins):
        arrived = [t for t in trips if t.arrival_s >= 0 and min(int(t.arrival_s // bin_s), bins - 1) == b]
        rows.append(
            {
                "bin_start_s": b * bin_s,
                "bin_end_s": (b + 1) * bin_s,
                "throughput_veh_per_h": loops[b] * 3600.0 / bin_s,
                "engine_throughput_veh_per_h": counts.crossed[b] * 3600.0 / bin_s,
                "mean_speed_mps": dist[b] / time[b] if time[b] > 0 else math.nan,
                "vehicle_km": dist[b] / 1000.0,
                "hard_brakes": counts.hard_brakes[b],
                "hard_brakes_per_1000_veh_km": _per_1000_km(counts.hard_brakes[b], dist[b]),
                "collisions": counts.sumo_collisions[b] + counts.geometric_collisions[b],
                "teleports": counts.teleports[b],
                "insertion_backlog": backlog[b],
                "arrived": len(arrived),
                **trip_columns(arrived),
            }
        )
    return rows


def run_row(folder: Path, counts: EngineCounts, duration_s: float, warmup_s: float = 0.0) -> Row:
    """The run's flow statistics (``flows.csv``'s statistics columns), measured after ``warmup_s`` (a
    whole number of bins: the road filling up from empty is left out): cars past the merge point, metres
    driven, hard brakes, collisions and teleports in the bins after it, trips that arrived after it, the
    depart delay of cars due after it. The collisions SUMO saw are split by how many of the two cars were
    automated (``geometric_collisions``, those only the loop found, always involve one). ``sumo_collisions_total`` and ``sumo_teleports_total`` are SUMO's
    own totals over the whole run (its statistics output), a cross-check of the loop's per-step count."""
    bin_s = duration_s / counts.bins
    w = round(warmup_s / bin_s)
    window_s = duration_s - w * bin_s
    loops = read_loops(folder, bin_s, counts.bins)[w:]
    dist, time = (part[w:] for part in read_edgedata(folder, bin_s, counts.bins))
    stats = read_statistics(folder)
    trips = read_trips(folder)
    collisions = read_collisions(folder)
    measured = [t for t in trips if t.arrival_s >= warmup_s]
    metres, brakes = sum(dist), sum(counts.hard_brakes[w:])
    geometric = sum(counts.geometric_collisions[w:])
    return {
        "warmup_s": warmup_s,
        "inserted": stats["inserted"],
        "automated": sum(t.automated for t in trips),
        "arrived": sum(t.arrival_s >= 0 for t in trips),
        "throughput_veh_per_h": sum(loops) * 3600.0 / window_s,
        "engine_throughput_veh_per_h": sum(counts.crossed[w:]) * 3600.0 / window_s,
        **trip_columns(measured),
        "mean_depart_delay_s": _mean([t.depart_delay_s for t in trips if t.depart_s >= warmup_s]),
        "mean_speed_mps": sum(dist) / sum(time) if sum(time) > 0 else math.nan,
        "vehicle_km": metres / 1000.0,
        "hard_brakes": brakes,
        "hard_brakes_per_1000_veh_km": _per_1000_km(brakes, metres),
        "collisions": sum(counts.sumo_collisions[w:]) + geometric,
        **{
            f"collisions_{name}": sum(1 for t, k in collisions if t >= warmup_s and k == n)
            for n, name in enumerate(("between_human", "automated_human", "between_automated"))
        },
        "geometric_collisions": geometric,
        "teleports": sum(counts.teleports[w:]),
        "sumo_collisions_total": stats["collisions"],
        "sumo_teleports_total": stats["teleports"],
        "insertion_backlog": stats["waiting"],
        "max_insertion_backlog": max(read_backlog(folder, bin_s, counts.bins)[w:]),
    }


__all__ = [
    "EngineCounts",
    "Row",
    "Trip",
    "bin_rows",
    "read_statistics",
    "read_trips",
    "run_row",
    "trip_columns",
]
