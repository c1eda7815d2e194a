"""Scenarios: which vehicles start where, how fast, with which driver type and road priority.

A scenario is either drawn by ``generate_scenario`` from a seed (docs/design-notes.md, "Definitions") or read from a
TOML file in ``scenarios/`` with ``load_scenario``. Positions are measured from each road's start;
the merge point lies at the end of each incoming road.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from idas_sumo.config import from_dict, load_toml
from idas_sumo.errors import InputError
from idas_sumo.physics.idm import DEFAULT_IDM
from idas_sumo.sim.backend import VEHICLE_LENGTH_M

Road = Literal["main", "merge"]
ROADS: tuple[Road, ...] = ("main", "merge")
B_TYPE_RANGE = (-2.0, 2.0)


@dataclass(frozen=True)
class VehicleSpec:
    """One vehicle at the start of an episode."""

    id: str
    road: Road
    start_pos_m: float
    """Front bumper position, metres from the start of its road."""
    speed_mps: float
    b_type: float = 0.0
    """Driver type in [-2, 2]: -2 least cooperative, 2 most."""
    controlled: bool = True
    """True: driven by a policy through the adapter; False: a SUMO-driven robot car."""
    depart_s: float = 0.0
    """When the vehicle enters, in simulated seconds."""

    def __post_init__(self) -> None:
        lo, hi = B_TYPE_RANGE
        if not (lo <= self.b_type <= hi):
            raise ValueError(f"vehicle {self.id!r}: b_type {self.b_type} outside [{lo}, {hi}]")
        if self.speed_mps < 0:
            raise ValueError(f"vehicle {self.id!r}: negative speed_mps {self.speed_mps}")
        if self.start_pos_m < VEHICLE_LENGTH_M:
            raise ValueError(
                f"vehicle {self.id!r}: start_pos_m {self.start_pos_m} must be at least the "
                f"vehicle length ({VEHICLE_LENGTH_M} m)"
            )
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
        for key in ("main_prio", "merge_prio"):
            if getattr(self, key) not in (0, 1):
                raise ValueError(f"{key} must be 0 or 1, got {getattr(self, key)}")
        ids = [v.id for v in self.vehicles]
        if len(set(ids)) != len(ids):
            raise ValueError("vehicle ids must be unique")
        if not self.vehicles:
            raise ValueError("a scenario needs at least one vehicle")
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


@dataclass(frozen=True)
class TrafficConfig:
    """How random scenarios are drawn (docs/design-notes.md, "Definitions"; ours where the paper is silent)."""

    min_vehicles_per_road: int = 2
    max_vehicles_per_road: int = 8
    start_range_m: float = 200.0
    """Start positions lie in [vehicle length, start_range_m] from each road's start."""
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
    p_main_priority: float = 0.8
    """Probability of priorities (main 1, merge 0); otherwise both roads share one priority."""
    max_controlled: int = 0
    """0: every vehicle is controlled; n > 0: at most n random vehicles are, the rest are robot cars."""

    def __post_init__(self) -> None:
        if not 1 <= self.min_vehicles_per_road <= self.max_vehicles_per_road:
            raise ValueError("need 1 <= min_vehicles_per_road <= max_vehicles_per_road")
        if not 0.0 <= self.min_speed_frac <= self.max_speed_frac <= 1.0:
            raise ValueError("need 0 <= min_speed_frac <= max_speed_frac <= 1")
        if not 0.0 <= self.p_main_priority <= 1.0:
            raise ValueError("p_main_priority must lie in [0, 1]")
        if self.max_controlled < 0:
            raise ValueError("max_controlled must be >= 0")
        room = self.start_range_m - VEHICLE_LENGTH_M
        if room < (self.max_vehicles_per_road - 1) * (self.min_start_gap_m + VEHICLE_LENGTH_M):
            raise ValueError("start_range_m is too short for max_vehicles_per_road at min_start_gap_m")


def generate_scenario(
    rng: np.random.Generator,
    traffic: TrafficConfig,
    speed_limits_mps: dict[Road, float],
    name: str = "random",
) -> Scenario:
    """Draw one random scenario; all randomness comes from ``rng``."""
    if rng.random() < traffic.p_main_priority:
        main_prio, merge_prio = 1, 0
    else:
        main_prio = merge_prio = int(rng.integers(0, 2))
    vehicles: list[VehicleSpec] = []
    for road in ROADS:
        n = int(rng.integers(traffic.min_vehicles_per_road, traffic.max_vehicles_per_road + 1))
        # Spread n cars over the range with at least the minimum gap: place them with the gaps removed,
        # then add the gaps back (uniform over all valid arrangements, no rejection loop).
        pitch = VEHICLE_LENGTH_M + traffic.min_start_gap_m
        slack = traffic.start_range_m - VEHICLE_LENGTH_M - (n - 1) * pitch
        offsets = np.sort(rng.uniform(0.0, slack, size=n))
        positions = VEHICLE_LENGTH_M + offsets + np.arange(n) * pitch
        limit = speed_limits_mps[road]
        speeds = rng.uniform(traffic.min_speed_frac, traffic.max_speed_frac, size=n) * limit
        if traffic.start_without_braking:
            speeds = _speeds_without_braking(positions, speeds)
        types = rng.uniform(*B_TYPE_RANGE, size=n)
        for i in range(n):
            vehicles.append(
                VehicleSpec(
                    id=f"{road}{i}",
                    road=road,
                    start_pos_m=round(float(positions[i]), 3),
                    speed_mps=round(float(speeds[i]), 3),
                    b_type=round(float(types[i]), 3),
                )
            )
    if traffic.max_controlled > 0 and len(vehicles) > traffic.max_controlled:
        chosen = set(rng.choice(len(vehicles), size=traffic.max_controlled, replace=False).tolist())
        vehicles = [
            VehicleSpec(v.id, v.road, v.start_pos_m, v.speed_mps, v.b_type, i in chosen, v.depart_s)
            for i, v in enumerate(vehicles)
        ]
    return Scenario(name=name, vehicles=tuple(vehicles), main_prio=main_prio, merge_prio=merge_prio)


def _speeds_without_braking(positions_m: np.ndarray, speeds_mps: np.ndarray) -> np.ndarray:
    """Cap speeds, front car first, so each follower's IDM desired gap s* fits its bumper gap.

    s* = s0 + v·T + v·(v - v_lead)/(2·sqrt(a·b)) <= gap is a quadratic in v: A·v² + B·v + (s0 - gap) <= 0
    with A = 1/(2·sqrt(a·b)) and B = T - A·v_lead; its larger root is the fastest allowed start speed.
    """
    p = DEFAULT_IDM
    a_coef = 1.0 / (2.0 * math.sqrt(p.max_accel_mps2 * p.comfortable_decel_mps2))
    capped = speeds_mps.copy()
    for i in range(len(capped) - 2, -1, -1):  # positions ascend: car i + 1 is car i's leader
        gap = positions_m[i + 1] - positions_m[i] - VEHICLE_LENGTH_M
        b_coef = p.time_headway_s - a_coef * capped[i + 1]
        c_coef = p.min_gap_m - gap
        fastest = (-b_coef + math.sqrt(b_coef * b_coef - 4.0 * a_coef * c_coef)) / (2.0 * a_coef)
        capped[i] = min(capped[i], fastest)
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


def check_against_net(
    scenario: Scenario,
    speed_limits_mps: dict[Road, float],
    road_length_m: dict[Road, float] | None,
    where: str,
) -> None:
    """Refuse insertion speeds above the road limit and positions beyond the road's end."""
    for v in scenario.vehicles:
        limit = speed_limits_mps[v.road]
        if v.speed_mps > limit + 1e-9:
            raise InputError(
                f"{where}: vehicle {v.id!r} starts at {v.speed_mps} m/s, above the {v.road} road's limit {limit} m/s"
            )
        if road_length_m is not None and v.start_pos_m > road_length_m[v.road]:
            raise InputError(
                f"{where}: vehicle {v.id!r} starts at {v.start_pos_m} m, beyond the {v.road} road's "
                f"length {road_length_m[v.road]} m"
            )
