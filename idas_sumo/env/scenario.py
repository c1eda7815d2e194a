"""Scenarios: which vehicles start where, how fast, with which driver type and road priority.

A scenario is either drawn by ``generate_scenario`` from a seed (docs/design-notes.md, "Definitions") or read from a
TOML file in ``scenarios/`` with ``load_scenario``. Positions are measured from each road's start,
along its edges (on a net whose approach has several, the junction-internal lanes between them count
nothing: ``Approach.edge_point``, so no car starts on one); the merge point lies at the end of each
incoming road.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from idas_sumo.config import MAX_VEHICLES, from_dict, load_toml
from idas_sumo.env.actions import MIN_ACCEL_MPS2
from idas_sumo.errors import InputError
from idas_sumo.physics.idm import DEFAULT_IDM
from idas_sumo.sim.backend import STEP_LENGTH_S, VEHICLE_LENGTH_M
from idas_sumo.sim.merge_detect import MergeSite

Road = Literal["main", "merge"]
ROADS: tuple[Road, ...] = ("main", "merge")
B_TYPE_RANGE = (-2.0, 2.0)
_BAD_ID_CHARS = "<>&\"'"  # XML's special characters: SUMO's route file quotes ids in attributes


def check_scenario_name(name: str) -> None:
    """A scenario's name becomes part of file names (``evaluate --sumo-output``): checked as vehicle ids
    are, and it must name a file, not a path (no ``/``, ``\\``, ``..``), so no output escapes ``--out``."""
    bad = [c for c in name if c in _BAD_ID_CHARS or c in "/\\" or not c.isprintable()]
    if not name.strip() or name in (".", "..") or bad:
        raise ValueError(
            f"scenario name {name!r} must be a file name: non-empty, without /, \\, control characters "
            f"or any of {_BAD_ID_CHARS} (it names the episode's output files)"
        )


@dataclass(frozen=True)
class VehicleSpec:
    """One vehicle at the start of an episode."""

    id: str
    road: Road
    start_pos_m: float
    """Front bumper position, metres from the start of its road (along its edges). Under a car length
    the body reaches back past the road's start, as SUMO inserts it: how a car enters a road whose
    edges hold less than a car."""
    speed_mps: float
    b_type: float = 0.0
    """Driver type in [-2, 2]: -2 least cooperative, 2 most."""
    controlled: bool = True
    """True: driven by a policy through the adapter; False: a SUMO-driven robot car."""
    depart_s: float = 0.0
    """When the vehicle enters, in simulated seconds."""

    def __post_init__(self) -> None:
        if not self.id or any(c in _BAD_ID_CHARS or c.isspace() for c in self.id):
            raise ValueError(
                f"vehicle id {self.id!r} must be non-empty, without spaces or any of {_BAD_ID_CHARS} "
                "(it goes into SUMO's route file)"
            )
        lo, hi = B_TYPE_RANGE
        if not (lo <= self.b_type <= hi):
            raise ValueError(f"vehicle {self.id!r}: b_type {self.b_type} outside [{lo}, {hi}]")
        if self.speed_mps < 0:
            raise ValueError(f"vehicle {self.id!r}: negative speed_mps {self.speed_mps}")
        if self.start_pos_m <= 0.0:
            raise ValueError(f"vehicle {self.id!r}: start_pos_m {self.start_pos_m} must be positive")
        if self.depart_s < 0:
            raise ValueError(f"vehicle {self.id!r}: negative depart_s {self.depart_s}")
        for name in ("start_pos_m", "speed_mps", "b_type", "depart_s"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"vehicle {self.id!r}: {name} must be finite")


@dataclass(frozen=True)
class Scenario:
    """A whole episode's start: road priorities and vehicles."""

    name: str
    vehicles: tuple[VehicleSpec, ...]
    main_prio: int = 1
    merge_prio: int = 0

    def __post_init__(self) -> None:
        check_scenario_name(self.name)
        for key in ("main_prio", "merge_prio"):
            if getattr(self, key) not in (0, 1):
                raise ValueError(f"{key} must be 0 or 1, got {getattr(self, key)}")
        ids = [v.id for v in self.vehicles]
        if len(set(ids)) != len(ids):
            raise ValueError("vehicle ids must be unique")
        if not self.vehicles:
            raise ValueError("a scenario needs at least one vehicle")
        if len(self.vehicles) > MAX_VEHICLES:
            raise ValueError(f"a scenario holds at most {MAX_VEHICLES} vehicles, got {len(self.vehicles)}")
        for road in ROADS:
            on_road = sorted(
                (v for v in self.vehicles if v.road == road and v.depart_s == 0.0),
                key=lambda v: v.start_pos_m,
            )
            for back, front in itertools.pairwise(on_road):
                if front.start_pos_m - back.start_pos_m < VEHICLE_LENGTH_M:
                    raise ValueError(f"vehicles {back.id!r} and {front.id!r} overlap on the {road} road")

    def prio(self, road: Road) -> int:
        return self.main_prio if road == "main" else self.merge_prio

    @property
    def controlled_ids(self) -> tuple[str, ...]:
        return tuple(v.id for v in self.vehicles if v.controlled)


MIN_ENTRY_SPEED_FOR_SPACING_MPS = 1.0
"""Ours: the least speed the generator assumes of a car ahead when it spaces a later entry behind it
(a car drawn at a standstill still moves off; without a floor it would never make room)."""

FEASIBLE_LEADER_FLOOR_MPS = 3.0
"""Ours: the speed the car ahead of a "feasible" entry is assumed to slow to, no lower. Chosen on entry delays
(1,000 scenarios of seed 777): a 1 m/s floor put 201 of 3,980 later entries past 30 s and 6 past the 60 s
evaluation episode; 3 m/s one past 30 s and none past 60 s."""

Entries = Literal["as_drawn", "feasible"]
"""How a later entry is spaced behind the car ahead of it on its road (``TrafficConfig.entries``)."""


@dataclass(frozen=True)
class TrafficConfig:
    """How random scenarios are drawn (docs/design-notes.md, "Definitions"; ours where the paper is silent).

    The defaults are the paper's traffic (L211, L225): ``n_vehicles`` = 8 cars split at random over the
    two roads, each either on the road at t = 0 or entering later at its road's start. ``n_vehicles``
    = 0 is the first generator: per road a count in [min_vehicles_per_road, max_vehicles_per_road],
    every car on the road at t = 0 (``scenarios/eval_dense.toml``; the entry keys are unused there).
    """

    n_vehicles: int = 8
    """Cars in a scenario, over both roads (paper: eight agents in the intelligent world, L211); the
    number on the main road is uniform over the splits that respect the per-road bounds. 0: per-road
    counts, all at t = 0 (the first generator)."""
    min_vehicles_per_road: int = 1
    max_vehicles_per_road: int = 8
    """Bounds on each road's count (with ``n_vehicles`` > 0 they bound the split)."""
    p_depart_later: float = 0.5
    """Ours: the probability that a car enters later, at its road's start, instead of being on the road
    (at a random position) at t = 0 (paper L225: the time each agent enters is random)."""
    max_depart_s: float = 10.0
    """Ours: later entries are drawn uniform in (0, max_depart_s] simulated seconds, then delayed where
    needed so that a car enters ``min_start_gap_m`` behind the car ahead of it on its road (that car
    assumed at constant speed since its own start), at a speed that forces no brake at insertion."""
    start_range_m: float = 200.0
    """Start positions at t = 0 lie in [vehicle length, start_range_m] from each road's start."""
    min_start_gap_m: float = 15.0
    """Bumper-to-bumper spacing is at least this much at insertion."""
    min_speed_frac: float = 0.6
    max_speed_frac: float = 1.0
    """Initial speeds are a uniform fraction of the road's limit."""
    start_without_braking: bool = True
    """Ours: cap each follower's start speed so the gap it starts with is at least its IDM desired gap to
    its leader. Otherwise a car can start inside the safety mask's braking region: with the 15 m minimum
    gap, 25 of the first 40 paper-suite scenarios forced a hard brake in their first step, whatever the
    method (docs/design-notes.md). False: speeds as drawn."""
    entries: Entries = "feasible"
    """Ours (issue 36: an entering car must not start in a brake its own mask forces). "feasible": the car ahead
    is assumed to have slowed as hard as it may without a hard brake (MIN_ACCEL_MPS2, down to
    FEASIBLE_LEADER_FLOOR_MPS) since its start; the entry waits until that car would be ``min_start_gap_m``
    ahead, and enters no faster than IDM allows behind it. "as_drawn" (the generator before issue 36, with
    which the shipped policies were trained and most tables of docs/results.md drawn): the car ahead assumed
    at constant speed since its own start; when it slowed, the entering car can start inside its own mask's
    braking region and meet a forced hard brake before it has chosen anything."""
    p_main_priority: float = 0.8
    """Probability of priorities (main 1, merge 0); otherwise both roads share one priority, 1 or 0 with
    equal probability (paper L64, L275: equal priority is possible)."""
    max_controlled: int = 0
    """0: every vehicle is controlled; n > 0: at most n random vehicles are, the rest are robot cars."""

    def __post_init__(self) -> None:
        if not 1 <= self.min_vehicles_per_road <= self.max_vehicles_per_road:
            raise ValueError("need 1 <= min_vehicles_per_road <= max_vehicles_per_road")
        if self.n_vehicles > MAX_VEHICLES or 2 * self.max_vehicles_per_road > MAX_VEHICLES:
            what = "n_vehicles" if self.n_vehicles > MAX_VEHICLES else "2 * max_vehicles_per_road"
            raise ValueError(
                f"{what} must be at most {MAX_VEHICLES} (the cars of one scenario), got "
                f"{self.n_vehicles if what == 'n_vehicles' else 2 * self.max_vehicles_per_road}"
            )
        if self.n_vehicles < 0:
            raise ValueError(f"n_vehicles must be >= 0, got {self.n_vehicles}")
        if self.n_vehicles and not (
            2 * self.min_vehicles_per_road <= self.n_vehicles <= 2 * self.max_vehicles_per_road
        ):
            raise ValueError(
                f"n_vehicles {self.n_vehicles} cannot be split over two roads with "
                f"{self.min_vehicles_per_road} to {self.max_vehicles_per_road} per road "
                "(set n_vehicles, or n_vehicles = 0 for per-road counts, all on the road at t = 0)"
            )
        if not 0.0 <= self.p_depart_later <= 1.0:
            raise ValueError("p_depart_later must lie in [0, 1]")
        if not self.max_depart_s >= 0.0:
            raise ValueError(f"max_depart_s must be >= 0, got {self.max_depart_s}")
        if self.p_depart_later > 0.0 and self.max_depart_s == 0.0:
            raise ValueError("p_depart_later > 0 needs max_depart_s > 0")
        if not 0.0 <= self.min_speed_frac <= self.max_speed_frac <= 1.0:
            raise ValueError("need 0 <= min_speed_frac <= max_speed_frac <= 1")
        if not 0.0 <= self.p_main_priority <= 1.0:
            raise ValueError("p_main_priority must lie in [0, 1]")
        if self.entries not in ("as_drawn", "feasible"):
            raise ValueError(f"entries must be 'as_drawn' or 'feasible', got {self.entries!r}")
        if self.max_controlled < 0:
            raise ValueError("max_controlled must be >= 0")
        room = self.start_range_m - VEHICLE_LENGTH_M
        if room < (self.max_on_one_road - 1) * (self.min_start_gap_m + VEHICLE_LENGTH_M):
            raise ValueError("start_range_m is too short for max_vehicles_per_road at min_start_gap_m")

    @property
    def max_on_one_road(self) -> int:
        """The most cars one road can get."""
        if self.n_vehicles:
            return min(self.max_vehicles_per_road, self.n_vehicles - self.min_vehicles_per_road)
        return self.max_vehicles_per_road

    @property
    def max_total(self) -> int:
        """The most cars a scenario can have."""
        return self.n_vehicles or 2 * self.max_vehicles_per_road


@dataclass(frozen=True)
class _RoadRoom:
    """Where one road's cars start: at t = 0 front bumpers in [car length, ``reach_m``], at most
    ``fits`` of them; later entries at ``entry_m``."""

    reach_m: float
    fits: int
    entry_m: float = VEHICLE_LENGTH_M


def _road_room(traffic: TrafficConfig, room_m: float | None) -> _RoadRoom | None:
    """None where the road holds the whole start range with a car to spare (every shipped and
    generated net): the draw is the one it always was. On a shorter road the starts at t = 0 reach a car
    short of its edges' end, and a road whose edges hold less than two cars takes its entries half way
    along them (the body reaching back past its start)."""
    if room_m is None or room_m - VEHICLE_LENGTH_M >= traffic.start_range_m:
        return None
    reach = room_m - VEHICLE_LENGTH_M
    pitch = VEHICLE_LENGTH_M + traffic.min_start_gap_m
    fits = 0 if reach < VEHICLE_LENGTH_M else int((reach - VEHICLE_LENGTH_M) // pitch) + 1
    return _RoadRoom(reach, fits, min(VEHICLE_LENGTH_M, math.floor(room_m * 500.0) / 1000.0))


def generate_scenario(
    rng: np.random.Generator,
    traffic: TrafficConfig,
    speed_limits_mps: dict[Road, float],
    name: str = "random",
    start_room_m: Mapping[Road, float] | None = None,
) -> Scenario:
    """Draw one random scenario; all randomness comes from ``rng``. ``start_room_m``: each road's room
    along its edges (``start_room_m(site)``); a road shorter than the start range takes the cars that do
    not fit on it as later entries at its start (None: every road holds the start range)."""
    rooms = {
        road: _road_room(traffic, None if start_room_m is None else start_room_m[road]) for road in ROADS
    }
    if rng.random() < traffic.p_main_priority:
        main_prio, merge_prio = 1, 0
    else:
        main_prio = merge_prio = int(rng.integers(0, 2))
    if traffic.n_vehicles:
        vehicles = _staggered_vehicles(rng, traffic, speed_limits_mps, rooms)
    else:
        vehicles = _vehicles_at_start(rng, traffic, speed_limits_mps, rooms)
    if traffic.max_controlled > 0 and len(vehicles) > traffic.max_controlled:
        chosen = set(rng.choice(len(vehicles), size=traffic.max_controlled, replace=False).tolist())
        vehicles = [
            VehicleSpec(v.id, v.road, v.start_pos_m, v.speed_mps, v.b_type, i in chosen, v.depart_s)
            for i, v in enumerate(vehicles)
        ]
    return Scenario(name=name, vehicles=tuple(vehicles), main_prio=main_prio, merge_prio=merge_prio)


def _start_positions(rng: np.random.Generator, traffic: TrafficConfig, n: int, reach_m: float) -> np.ndarray:
    """n front-bumper positions in [vehicle length, reach_m], ascending, at least the minimum gap
    apart: placed with the gaps removed, then the gaps added back (uniform over all valid arrangements,
    no rejection loop)."""
    pitch = VEHICLE_LENGTH_M + traffic.min_start_gap_m
    slack = reach_m - VEHICLE_LENGTH_M - (n - 1) * pitch
    offsets = np.sort(rng.uniform(0.0, slack, size=n))
    return np.asarray(VEHICLE_LENGTH_M + offsets + np.arange(n) * pitch)


def _vehicles_at_start(
    rng: np.random.Generator,
    traffic: TrafficConfig,
    speed_limits_mps: dict[Road, float],
    rooms: Mapping[Road, _RoadRoom | None],
) -> list[VehicleSpec]:
    """The first generator: per road a random count, every car on the road at t = 0 (on a short road
    those that do not fit enter at its start as soon as the car ahead leaves room)."""
    vehicles: list[VehicleSpec] = []
    for road in ROADS:
        n = int(rng.integers(traffic.min_vehicles_per_road, traffic.max_vehicles_per_road + 1))
        room = rooms[road]
        if room is not None and n > room.fits:
            later = n - room.fits
            vehicles += _road_vehicles(
                rng, traffic, road, speed_limits_mps[road], n, later, room, draw_times=False
            )
            continue
        positions = _start_positions(rng, traffic, n, traffic.start_range_m if room is None else room.reach_m)
        limit = speed_limits_mps[road]
        speeds = rng.uniform(traffic.min_speed_frac, traffic.max_speed_frac, size=n) * limit
        if traffic.start_without_braking:
            speeds = _speeds_without_braking(positions, speeds)
        types = rng.uniform(*B_TYPE_RANGE, size=n)
        vehicles += [_drawn_vehicle(road, i, positions[i], speeds[i], types[i]) for i in range(n)]
    return vehicles


def _drawn_vehicle(
    road: Road, index: int, start_m: float, speed_mps: float, b_type: float, depart_s: float = 0.0
) -> VehicleSpec:
    """A generated car, its numbers rounded to mm, mm/s and ms as scenario files write them."""
    return VehicleSpec(
        id=f"{road}{index}",
        road=road,
        start_pos_m=round(float(start_m), 3),
        speed_mps=round(float(speed_mps), 3),
        b_type=round(float(b_type), 3),
        depart_s=round(float(depart_s), 3),
    )


def _staggered_vehicles(
    rng: np.random.Generator,
    traffic: TrafficConfig,
    speed_limits_mps: dict[Road, float],
    rooms: Mapping[Road, _RoadRoom | None],
) -> list[VehicleSpec]:
    """The paper's traffic: ``n_vehicles`` split over the roads; each car on the road at t = 0 or, with
    probability ``p_depart_later``, entering at its road's start at a random time (see TrafficConfig;
    on a short road also every car that does not fit on it at t = 0).

    Ids: per road, the cars at t = 0 from the back (``main0`` …), then the later ones in entry order.
    """
    total = traffic.n_vehicles
    lo = max(traffic.min_vehicles_per_road, total - traffic.max_vehicles_per_road)
    hi = min(traffic.max_vehicles_per_road, total - traffic.min_vehicles_per_road)
    n_main = int(rng.integers(lo, hi + 1))
    vehicles: list[VehicleSpec] = []
    counts: dict[Road, int] = {"main": n_main, "merge": total - n_main}
    for road, n in counts.items():
        n_later = int(np.count_nonzero(rng.random(n) < traffic.p_depart_later))
        room = rooms[road]
        if room is not None:
            n_later = max(n_later, n - room.fits)
        vehicles += _road_vehicles(rng, traffic, road, speed_limits_mps[road], n, n_later, room)
    return vehicles


def _road_vehicles(
    rng: np.random.Generator,
    traffic: TrafficConfig,
    road: Road,
    limit: float,
    n: int,
    n_later: int,
    room: _RoadRoom | None,
    draw_times: bool = True,
) -> list[VehicleSpec]:
    """One road's ``n`` cars, ``n_later`` of them entering later at its start: at times drawn uniform in
    (0, max_depart_s] (``draw_times``; else at once), each delayed to enter behind the car ahead."""
    reach, entry = (traffic.start_range_m, VEHICLE_LENGTH_M) if room is None else (room.reach_m, room.entry_m)
    n_now = n - n_later
    positions = _start_positions(rng, traffic, n_now, reach)
    speeds = rng.uniform(traffic.min_speed_frac, traffic.max_speed_frac, size=n) * limit
    if traffic.start_without_braking:
        speeds[:n_now] = _speeds_without_braking(positions, speeds[:n_now])
    types = rng.uniform(*B_TYPE_RANGE, size=n)
    # (0, max]: a draw of exactly 0 would put a later car on the road at t = 0 at the road's start.
    wanted = np.sort(traffic.max_depart_s * (1.0 - rng.random(n_later))) if draw_times else np.zeros(n_later)
    departs = np.zeros(n)
    starts = np.concatenate([positions, np.full(n_later, entry)])
    # The car ahead of the next entry: the rearmost car on the road at t = 0, then each entry in turn.
    ahead: tuple[float, float, float] | None = None  # (position at its start m, speed m/s, start s)
    if n_now:
        ahead = (float(positions[0]), float(speeds[0]), 0.0)
    for m in range(n_later):
        i = n_now + m
        if traffic.entries == "feasible" and ahead is not None:
            t, speeds[i] = _feasible_entry(
                float(wanted[m]), float(speeds[i]), ahead, traffic.min_start_gap_m, entry
            )
        else:
            t, speeds[i] = _entry_as_drawn(float(wanted[m]), float(speeds[i]), ahead, traffic, entry)
        departs[i] = t
        ahead = (entry, float(speeds[i]), t)
    return [_drawn_vehicle(road, i, starts[i], speeds[i], types[i], departs[i]) for i in range(n)]


def _on_step(t: float) -> float:
    """``t`` rounded up to a step boundary: SUMO inserts on one, so the spacing holds when the car appears."""
    return math.ceil(round(t / STEP_LENGTH_S, 9)) * STEP_LENGTH_S


def _entry_as_drawn(
    wanted_s: float,
    speed_mps: float,
    ahead: tuple[float, float, float] | None,
    traffic: TrafficConfig,
    entry_m: float,
) -> tuple[float, float]:
    """(depart s, speed m/s) of a later entry at ``entry_m``, the car ahead (position at its start m, speed
    m/s, start s) assumed at constant speed (at least MIN_ENTRY_SPEED_FOR_SPACING_MPS) since its start."""
    t = wanted_s
    if ahead is not None:
        pos, speed, t0 = ahead
        speed = max(speed, MIN_ENTRY_SPEED_FOR_SPACING_MPS)
        room_needed = entry_m + VEHICLE_LENGTH_M + traffic.min_start_gap_m - pos
        t = max(t, t0 + room_needed / speed)
    t = _on_step(t)
    if ahead is not None and traffic.start_without_braking:
        pos, speed, t0 = ahead
        gap = pos + max(speed, MIN_ENTRY_SPEED_FOR_SPACING_MPS) * (t - t0) - (VEHICLE_LENGTH_M + entry_m)
        speed_mps = min(speed_mps, _fastest_start(gap, speed))
    return t, speed_mps


def _slowest_leader(pos_m: float, speed_mps: float, elapsed_s: float) -> tuple[float, float]:
    """(position m, speed m/s) of a car ``elapsed_s`` after it was at ``pos_m`` with ``speed_mps``, had it
    slowed at MIN_ACCEL_MPS2 (the strongest deceleration short of a hard brake) down to
    FEASIBLE_LEADER_FLOOR_MPS and kept that speed."""
    floor = FEASIBLE_LEADER_FLOOR_MPS
    speed = max(speed_mps, floor)
    decel = -MIN_ACCEL_MPS2
    slowing_s = (speed - floor) / decel
    if elapsed_s <= slowing_s:
        return pos_m + speed * elapsed_s - 0.5 * decel * elapsed_s**2, speed - decel * elapsed_s
    return pos_m + (speed * speed - floor * floor) / (2.0 * decel) + floor * (elapsed_s - slowing_s), floor


def _feasible_entry(
    wanted_s: float, speed_mps: float, ahead: tuple[float, float, float], min_gap_m: float, entry_m: float
) -> tuple[float, float]:
    """(depart s, speed m/s) of a later entry at ``entry_m`` against the slowest the car ahead may have driven
    (``_slowest_leader``): the first step from ``wanted_s`` on where that car is ``min_gap_m`` ahead, at
    the drawn speed or the fastest whose IDM desired gap fits (``_fastest_start``), whichever is lower."""
    pos, speed, t0 = ahead
    t = _on_step(wanted_s)
    while True:
        leader_pos, leader_speed = _slowest_leader(pos, speed, t - t0)
        gap = leader_pos - (VEHICLE_LENGTH_M + entry_m)
        if gap >= min_gap_m:
            return t, min(speed_mps, _fastest_start(gap, leader_speed))
        t = _on_step(t + STEP_LENGTH_S)


def _fastest_start(gap_m: float, leader_speed_mps: float) -> float:
    """The fastest speed whose IDM desired gap s* fits ``gap_m`` behind a leader at ``leader_speed_mps``.

    s* = s0 + v·T + v·(v - v_lead)/(2·sqrt(a·b)) <= gap is a quadratic in v: A·v² + B·v + (s0 - gap) <= 0
    with A = 1/(2·sqrt(a·b)) and B = T - A·v_lead; its larger root is the fastest allowed start speed.
    """
    p = DEFAULT_IDM
    a_coef = 1.0 / (2.0 * math.sqrt(p.max_accel_mps2 * p.comfortable_decel_mps2))
    b_coef = p.time_headway_s - a_coef * leader_speed_mps
    c_coef = p.min_gap_m - gap_m
    return (-b_coef + math.sqrt(b_coef * b_coef - 4.0 * a_coef * c_coef)) / (2.0 * a_coef)


def _speeds_without_braking(positions_m: np.ndarray, speeds_mps: np.ndarray) -> np.ndarray:
    """Cap speeds, front car first, so each follower's IDM desired gap s* fits its bumper gap
    (``_fastest_start``)."""
    capped = speeds_mps.copy()
    for i in range(len(capped) - 2, -1, -1):  # positions ascend: car i + 1 is car i's leader
        gap = positions_m[i + 1] - positions_m[i] - VEHICLE_LENGTH_M
        capped[i] = min(capped[i], _fastest_start(gap, capped[i + 1]))
    return capped


@dataclass(frozen=True)
class _ScenarioFile:
    name: str = ""
    main_prio: int = 1
    merge_prio: int = 0
    vehicles: tuple[VehicleSpec, ...] = field(default_factory=tuple)


def load_scenario(path: str | Path, speed_limits_mps: dict[Road, float] | None = None) -> Scenario:
    """Read a scenario TOML; every problem is one InputError line naming the file."""
    p = Path(path)
    raw = from_dict(_ScenarioFile, load_toml(p), str(p))
    try:
        scenario = Scenario(
            name=raw.name or p.stem, vehicles=raw.vehicles, main_prio=raw.main_prio, merge_prio=raw.merge_prio
        )
    except ValueError as err:
        raise InputError(f"{p}: {err}") from None
    if speed_limits_mps is not None:
        check_against_net(scenario, speed_limits_mps, road_length_m=None, where=str(p))
    return scenario


def start_room_m(site: MergeSite) -> dict[Road, float]:
    """How far from its road's start a car may start: the summed length of the approach's edges
    (``start_pos_m`` counts along them, ``Approach.edge_point``); a one-edge road's whole length."""
    return {road: site.approach(road).edges_length_m for road in ROADS}


def check_against_net(
    scenario: Scenario,
    speed_limits_mps: dict[Road, float],
    road_length_m: dict[Road, float] | None,
    where: str,
) -> None:
    """Refuse insertion speeds above the road limit and positions beyond the road's end
    (``road_length_m``: ``start_room_m``, the room on its edges)."""
    for v in scenario.vehicles:
        limit = speed_limits_mps[v.road]
        if v.speed_mps > limit + 1e-9:
            raise InputError(
                f"{where}: vehicle {v.id!r} starts at {v.speed_mps} m/s, above the {v.road} road's limit {limit} m/s"
            )
        if road_length_m is not None and v.start_pos_m > road_length_m[v.road]:
            raise InputError(
                f"{where}: vehicle {v.id!r} starts at {v.start_pos_m} m, beyond the {v.road} road's "
                f"length {road_length_m[v.road]:g} m along its edges"
            )
