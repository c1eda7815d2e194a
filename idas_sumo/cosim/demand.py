"""What a co-simulation is asked to run: demand per road, penetration rates, durations (checked here once)."""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path

from idas_sumo.errors import InputError
from idas_sumo.sim.backend import STEP_LENGTH_S
from idas_sumo.sim.merge_detect import MergeSite, Side

MAX_VEH_PER_H_PER_LANE = 3600.0
"""More than one car a second per lane of an incoming road is no traffic a lane can carry (a lane's
capacity is about 1,800 to 2,400 veh/h): refused as a typo rather than left to pile up in SUMO's queue."""
MAX_DURATION_S = 24 * 3600.0
"""A simulated day at most."""
MAX_PENETRATIONS = 101
SIDES: tuple[Side, ...] = ("main", "merge")


def road_names(site: MergeSite) -> dict[str, Side]:
    """The names a road may be given by: its side as ``nets inspect`` prints it ('main', 'merge'), and
    the id of any of its own edges before the merge point (not one both approaches share)."""
    names: dict[str, Side] = {side: side for side in SIDES}
    shared = set(site.shared_lanes)
    for side in SIDES:
        for edge_id in site.approach(side).edge_ids:
            if edge_id not in shared:
                names.setdefault(edge_id, side)
    return names


def _lanes(site: MergeSite, side: Side) -> int:
    return max(lane.lane_count for lane in site.approach(side).edges)


def parse_demand(text: str, site: MergeSite, flag: str = "--demand") -> dict[Side, float]:
    """``main=1200,merge=600`` -> vehicles per hour per side. Every named road must be one of the merge's
    two (``road_names``), each at most once; a road left out has no traffic."""
    names = road_names(site)
    demand: dict[Side, float] = {}
    for part in text.split(","):
        m = re.fullmatch(r"\s*([^=\s]+)\s*=\s*(\S+)\s*", part)
        if m is None:
            raise InputError(f"{flag}: expected ROAD=VEH_PER_H[,ROAD=VEH_PER_H], got {text!r}")
        name, value = m.groups()
        if name not in names:
            raise InputError(
                f"{flag}: no road {name!r} at the merge {site.junction_id!r} of {site.path.name}; "
                f"roads: {', '.join(names)}"
            )
        side = names[name]
        if side in demand:
            raise InputError(f"{flag}: the {side} road is given twice in {text!r}")
        try:
            rate = float(value)
        except ValueError:
            raise InputError(f"{flag}: {name}={value}: expected vehicles per hour, a number") from None
        limit = MAX_VEH_PER_H_PER_LANE * _lanes(site, side)
        if not math.isfinite(rate) or rate < 0 or rate > limit:
            raise InputError(
                f"{flag}: {name}={value}: expected 0 to {limit:g} vehicles per hour "
                f"({MAX_VEH_PER_H_PER_LANE:g} per lane of the {side} road)"
            )
        demand[side] = rate
    if not any(demand.values()):
        raise InputError(f"{flag}: no traffic in {text!r} (every road at 0 vehicles per hour)")
    return demand


def demand_label(demand: dict[Side, float]) -> str:
    """``main=1200 merge=600``: the demand column of the CSVs (no comma, one cell)."""
    return " ".join(f"{side}={demand.get(side, 0.0):g}" for side in SIDES)


def parse_demands(texts: list[str], site: MergeSite) -> list[dict[Side, float]]:
    """Each ``--demand`` given (the flag repeats: one demand level each)."""
    demands = [parse_demand(t, site) for t in texts]
    labels = [demand_label(d) for d in demands]
    if len(set(labels)) != len(labels):
        raise InputError("--demand: the same demand is given twice")
    return demands


def parse_penetrations(text: str, flag: str = "--penetration") -> list[float]:
    """``0,0.25,0.5,1`` -> the penetration rates, each in [0, 1], none twice."""
    rates: list[float] = []
    for part in text.split(","):
        try:
            p = float(part)
        except ValueError:
            raise InputError(f"{flag}: expected rates in [0, 1] such as 0,0.5,1, got {text!r}") from None
        if not 0.0 <= p <= 1.0:
            raise InputError(f"{flag}: {part.strip()} is outside [0, 1] (the share of automated cars)")
        if p in rates:
            raise InputError(f"{flag}: {part.strip()} is given twice")
        rates.append(p)
    if len(rates) > MAX_PENETRATIONS:
        raise InputError(f"{flag}: more than {MAX_PENETRATIONS} rates")
    return rates


MAX_MULTIPLIER = 10.0
"""A profile step more than ten times the demand given is taken for a typo."""
MAX_PROFILE_STEPS = 1000


def _profile_rows(path: Path) -> list[list[str]]:
    try:
        with path.open(newline="", encoding="utf-8") as f:
            rows = [r for r in csv.reader(f) if any(c.strip() for c in r)]
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise InputError(f"--demand-profile: cannot read {path} ({err})") from None
    if not rows or [c.strip() for c in rows[0]] != ["time_s", "multiplier"]:
        raise InputError(f"--demand-profile: {path}: expected a CSV with the header time_s,multiplier")
    if not 2 <= len(rows) <= MAX_PROFILE_STEPS + 1:
        raise InputError(f"--demand-profile: {path}: expected 1 to {MAX_PROFILE_STEPS} rows after the header")
    return rows[1:]


def parse_profile(path: Path, duration_s: float) -> tuple[tuple[float, float], ...]:
    """A demand time profile from a CSV ``time_s,multiplier``: piecewise constant, each row's multiplier
    of every road's demand from its time until the next row's; the first row at 0, times increasing,
    whole steps, before the run's end; multipliers in [0, ``MAX_MULTIPLIER``]."""
    steps: list[tuple[float, float]] = []
    for n, row in enumerate(_profile_rows(path), start=2):
        where = f"--demand-profile: {path}, line {n}"
        try:
            t, m = (float(c) for c in row)
        except ValueError:
            raise InputError(
                f"{where}: expected two numbers time_s,multiplier, got {','.join(row)!r}"
            ) from None
        if not math.isfinite(t) or t < 0 or (not steps and t != 0) or (steps and t <= steps[-1][0]):
            raise InputError(f"{where}: times start at 0 and increase, got {t:g}")
        if t >= duration_s:
            raise InputError(f"{where}: {t:g} s is not before the end of the run ({duration_s:g} s)")
        if abs(t / STEP_LENGTH_S - round(t / STEP_LENGTH_S)) > 1e-6:
            raise InputError(f"{where}: {t:g} s is not a whole number of {STEP_LENGTH_S:g} s steps")
        if not math.isfinite(m) or not 0 <= m <= MAX_MULTIPLIER:
            raise InputError(f"{where}: expected a multiplier in [0, {MAX_MULTIPLIER:g}], got {m:g}")
        steps.append((t, m))
    return tuple(steps)


def check_profile_demand(
    demands: list[dict[Side, float]], profile: tuple[tuple[float, float], ...], site: MergeSite
) -> None:
    """Every demand times the profile's largest multiplier within a road's limit (as ``parse_demand``)."""
    peak = max((m for _, m in profile), default=1.0)
    for demand in demands:
        for side, rate in demand.items():
            limit = MAX_VEH_PER_H_PER_LANE * _lanes(site, side)
            if rate * peak > limit:
                raise InputError(
                    f"--demand-profile: {side}={rate:g} times {peak:g} is more than {limit:g} vehicles "
                    f"per hour ({MAX_VEH_PER_H_PER_LANE:g} per lane of the {side} road)"
                )


def profile_label(profile: tuple[tuple[float, float], ...]) -> str:
    """``0:1 600:1.5``: the demand_profile column (empty without a profile)."""
    return " ".join(f"{t:g}:{m:g}" for t, m in profile)


def check_duration(duration_s: float, bin_s: float, warmup_s: float = 0.0) -> None:
    """A run of at least one step and at most ``MAX_DURATION_S``, of whole steps; a bin of whole steps
    that divides it; a warm-up of whole bins that leaves at least one."""
    if not math.isfinite(duration_s) or not 0 < duration_s <= MAX_DURATION_S:
        raise InputError(
            f"--duration-s: expected a duration in (0, {MAX_DURATION_S:g}] s, got {duration_s:g}"
        )
    if not math.isfinite(bin_s) or not 0 < bin_s <= duration_s:
        raise InputError(f"--bin-s: expected a time bin in (0, --duration-s], got {bin_s:g}")
    for name, value in (("--duration-s", duration_s), ("--bin-s", bin_s)):
        steps = value / STEP_LENGTH_S
        if abs(steps - round(steps)) > 1e-6:
            raise InputError(f"{name}: {value:g} s is not a whole number of {STEP_LENGTH_S:g} s steps")
    bins = duration_s / bin_s
    if abs(bins - round(bins)) > 1e-9:
        raise InputError(
            f"--bin-s: {bin_s:g} s does not divide --duration-s {duration_s:g} s into whole bins"
        )
    warm = warmup_s / bin_s
    if not math.isfinite(warm) or warm < 0 or abs(warm - round(warm)) > 1e-9 or warmup_s >= duration_s:
        raise InputError(
            f"--warmup-s: expected whole bins of {bin_s:g} s shorter than --duration-s, got {warmup_s:g}"
        )


__all__ = [
    "MAX_VEH_PER_H_PER_LANE",
    "check_duration",
    "check_profile_demand",
    "demand_label",
    "parse_demand",
    "parse_demands",
    "parse_penetrations",
    "parse_profile",
    "profile_label",
    "road_names",
]
