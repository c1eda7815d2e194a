"""The driver-type sweep (paper Fig. 5(a) and 6; issue #15 item 4): its scenarios, and what it measures.

Set-up (ours where the paper is silent; docs/design-notes.md, "Definitions"): two cars, one per road, the main
road with priority, both on the road at t = 0 at the same speed, the merge car level with or a few metres
behind the main car in projection (equal distance to the merge point), so both reach the merging zone together
and the merge car is never ahead (Fig. 5(a), not 5(b)). Each start offset is drawn from the seed and used for
every b_type, so the b_types are compared on the same starts. The merge car runs the method with its b_type
swept over ``SWEEP_B_TYPES``; the main car runs ``--others`` (the shipped IDAS by default) with
``MAIN_CAR_B_TYPE``.

Measured per episode (episodes.csv): the merge car's merge time (it passes the merge point, from its entry) and
its mean speed until then. Per method: the direction of merge time against b_type and Spearman's rank
correlation over all episodes, its p-value from a permutation test (scipy is not a dependency).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import pandas as pd

from idas_sumo.env.scenario import B_TYPE_RANGE, Scenario, VehicleSpec
from idas_sumo.errors import InputError
from idas_sumo.sim.backend import VEHICLE_LENGTH_M

SWEEP_B_TYPES: tuple[float, ...] = tuple(float(x) for x in np.linspace(*B_TYPE_RANGE, 9))
"""The merge car's driver types, −2 to 2 in steps of 0.5."""
DEFAULT_SWEEP_OFFSETS = 10
"""Start offsets per b_type when ``evaluate --scenarios`` is not given for this suite."""
MAIN_CAR_B_TYPE = 0.0
"""The main car's driver type, fixed: only the merge car's changes."""
MAIN_DIST_TO_MERGE_M = (140.0, 170.0)
"""The main car starts this far before the merge point (uniform): about 10 s of driving, as in s1-s4."""
MERGE_LAG_M = (0.0, 6.0)
"""How far the merge car starts behind the main car in projection (uniform): level to about 0.5 s behind,
so both reach the merging zone together and the merge car is not ahead."""
SPEED_FRACTION = (0.8, 0.9)
"""Both cars' start speed, as a fraction of the lower of the two roads' speed limits (uniform)."""
MAIN_CAR_ID = "main_car"
MERGE_CAR_ID = "merge_car"
PERMUTATIONS = 10_000
"""Permutations of the test of the rank correlation (the smallest p it can give is 1/10001)."""
PERMUTATION_SEED = 0
"""The permutations' seed: fixed, so the same episodes give the same p-value."""
SIGNIFICANCE = 0.05
_NAME = re.compile(r"-btype[+-]\d+\.\d$")
"""Sweep scenarios end in -btype+0.5 (today's ``sweepNN-btype…``, and the earlier ``s1-btype…``)."""

DRIVER_TYPE_COLUMNS: tuple[str, ...] = (
    "method",
    "b_type",
    "episodes",
    "merged",
    "merge_time_mean_s",
    "merge_time_sd_s",
    "merge_time_min_s",
    "merge_time_max_s",
    "merge_speed_mean_mps",
    "collision_pct",
    "ego_success_pct",
)
TREND_COLUMNS: tuple[str, ...] = (
    "method",
    "episodes",
    "merged",
    "spearman_rho",
    "p_value",
    "permutations",
    "direction",
    "significant",
)


@dataclass(frozen=True)
class SweepCase:
    scenario: Scenario
    merge_car: str


def sweep_name(offset: int, b_type: float) -> str:
    return f"sweep{offset:02d}-btype{b_type:+.1f}"


def is_sweep_scenario(name: str) -> bool:
    return bool(_NAME.search(name))


def sweep_scenarios(
    n_offsets: int,
    seed: int,
    speed_limits_mps: Mapping[str, float],
    road_lengths_m: Mapping[str, float],
    b_types: Sequence[float] = SWEEP_B_TYPES,
) -> list[SweepCase]:
    """``n_offsets`` starts drawn from ``seed``, each with every b_type (offset by offset)."""
    speed_cap = min(speed_limits_mps["main"], speed_limits_mps["merge"])
    # The farthest start any offset can draw, and a car length behind it to the road's start.
    need_m = MAIN_DIST_TO_MERGE_M[1] + MERGE_LAG_M[1] + VEHICLE_LENGTH_M
    for road in ("main", "merge"):
        if road_lengths_m[road] < need_m:
            raise InputError(
                f"the driver-types suite needs roads of at least {need_m:g} m to the merge point; "
                f"the net's {road} road is {road_lengths_m[road]:g} m"
            )
    cases = []
    for k in range(n_offsets):
        rng = np.random.default_rng([seed, k])
        dist_main = float(rng.uniform(*MAIN_DIST_TO_MERGE_M))
        lag = float(rng.uniform(*MERGE_LAG_M))
        speed = round(float(rng.uniform(*SPEED_FRACTION)) * speed_cap, 3)
        starts = {
            "main": road_lengths_m["main"] - dist_main,
            "merge": road_lengths_m["merge"] - (dist_main + lag),
        }
        for b_type in b_types:
            vehicles = (
                VehicleSpec(MAIN_CAR_ID, "main", round(starts["main"], 3), speed, MAIN_CAR_B_TYPE),
                VehicleSpec(MERGE_CAR_ID, "merge", round(starts["merge"], 3), speed, float(b_type)),
            )
            scenario = Scenario(sweep_name(k, b_type), vehicles, main_prio=1, merge_prio=0)
            cases.append(SweepCase(scenario, MERGE_CAR_ID))
    return cases


# -- the rank correlation ----------------------------------------------------------------------------


def average_ranks(values: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Ranks 1..n; tied values share the mean of the ranks they occupy ([1, 2, 2, 3] -> [1, 2.5, 2.5, 4])."""
    x = np.asarray(values, dtype=np.float64)
    _, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
    ends = np.cumsum(counts)
    mean_rank = (ends - counts + 1 + ends) / 2.0
    return np.asarray(mean_rank[inverse.reshape(-1)], dtype=np.float64)


def spearman(x: npt.ArrayLike, y: npt.ArrayLike) -> float:
    """Spearman's rho: Pearson's correlation of the average ranks (NaN if either side is constant)."""
    dx, dy = _centred_ranks(x, y)
    denom = math.sqrt(float(dx @ dx) * float(dy @ dy))
    return float(dx @ dy) / denom if denom > 0 else math.nan


def spearman_test(
    x: npt.ArrayLike, y: npt.ArrayLike, permutations: int = PERMUTATIONS, seed: int = PERMUTATION_SEED
) -> tuple[float, float]:
    """(rho, two-sided p): p = (1 + permutations with |rho| at least the observed) / (1 + permutations),
    permuting y against x. NaN, NaN where rho is undefined."""
    dx, dy = _centred_ranks(x, y)
    denom = math.sqrt(float(dx @ dx) * float(dy @ dy))
    if denom == 0:
        return math.nan, math.nan
    rho = float(dx @ dy) / denom
    rng = np.random.default_rng(seed)
    at_least = 0
    chunk = max(1, 2_000_000 // max(len(dy), 1))  # bounds the memory of one block of permutations
    done = 0
    while done < permutations:
        m = min(chunk, permutations - done)
        shuffled = rng.permuted(np.tile(dy, (m, 1)), axis=1)
        r = (shuffled @ dx) / denom
        # A permutation that reproduces the observed rho up to rounding counts as "at least as extreme".
        at_least += int(np.count_nonzero(np.abs(r) >= abs(rho) - 1e-12))
        done += m
    return rho, (1 + at_least) / (1 + permutations)


def _centred_ranks(
    x: npt.ArrayLike, y: npt.ArrayLike
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    xa = np.asarray(x, dtype=np.float64)
    ya = np.asarray(y, dtype=np.float64)
    if xa.shape != ya.shape or xa.ndim != 1:
        raise ValueError(f"x and y must be 1-D of the same length, got {xa.shape} and {ya.shape}")
    rx, ry = average_ranks(xa), average_ranks(ya)
    return rx - rx.mean() if len(rx) else rx, ry - ry.mean() if len(ry) else ry


# -- the tables ----------------------------------------------------------------------------------------


def sweep_episodes(episodes: pd.DataFrame) -> pd.DataFrame:
    return episodes[episodes["scenario"].astype(str).map(is_sweep_scenario)]


def driver_type_rows(episodes: pd.DataFrame) -> list[dict[str, object]]:
    """``driver_types.csv``: per method and merge-car b_type (in the episodes' order: the suite runs b_types
    in increasing order), its merge times and mean speed to the merge point (over the episodes in which it
    got there), collisions and its own success."""
    rows: list[dict[str, object]] = []
    for (method, b_type), group in sweep_episodes(episodes).groupby(["method", "ego_type"], sort=False):
        merged = group["ego_merge_time_s"].dropna()
        rows.append(
            {
                "method": method,
                "b_type": b_type,
                "episodes": len(group),
                "merged": len(merged),
                "merge_time_mean_s": _round(merged.mean(), 3),
                "merge_time_sd_s": _round(merged.std(ddof=1), 3) if len(merged) > 1 else np.nan,
                "merge_time_min_s": _round(merged.min(), 3),
                "merge_time_max_s": _round(merged.max(), 3),
                "merge_speed_mean_mps": _round(group["ego_merge_speed_mps"].dropna().mean(), 3),
                "collision_pct": round(100.0 * float((group["collisions"] > 0).mean()), 2),
                "ego_success_pct": round(100.0 * float(group["ego_success"].mean()), 2),
            }
        )
    return rows


def trend_rows(
    episodes: pd.DataFrame, permutations: int = PERMUTATIONS, seed: int = PERMUTATION_SEED
) -> list[dict[str, object]]:
    """``driver_types_trend.csv``: per method, Spearman's rho of merge time against b_type over every
    episode in which the merge car passed the merge point, its p-value and the direction."""
    rows: list[dict[str, object]] = []
    for method, group in sweep_episodes(episodes).groupby("method", sort=False):
        merged = group.dropna(subset=["ego_merge_time_s"])
        rho, p = spearman_test(merged["ego_type"], merged["ego_merge_time_s"], permutations, seed)
        rows.append(
            {
                "method": method,
                "episodes": len(group),
                "merged": len(merged),
                "spearman_rho": _round(rho, 4),
                "p_value": _round(p, 5),
                "permutations": permutations,
                "direction": direction(rho),
                "significant": int(bool(p < SIGNIFICANCE)) if math.isfinite(p) else 0,
            }
        )
    return rows


def direction(rho: float) -> str:
    """How merge time moves as b_type grows, by the sign of rho."""
    if not math.isfinite(rho):
        return "undefined"
    return "rises" if rho > 0 else "falls" if rho < 0 else "flat"


def verdict(row: Mapping[str, object], label: str, others: str) -> str:
    """The one line printed per method: the direction only where the test finds one, the sign and the
    numbers always."""
    rho, p = float(row["spearman_rho"]), float(row["p_value"])  # type: ignore[arg-type]
    head = f"driver types, merge car {label} (main car {others}, b_type {MAIN_CAR_B_TYPE:g}): "
    merged = f"{row['merged']} of {row['episodes']} episodes merged"
    if not math.isfinite(rho):
        return f"{head}no rank correlation (the merge time does not vary, or too few merges; {merged})"
    numbers = (
        f"Spearman rho = {rho:+.3f}, p = {p:.4f} (permutation test, {row['permutations']} permutations; "
        f"{merged})"
    )
    if p < SIGNIFICANCE:
        return (
            f"{head}merge time {row['direction']} with b_type, significant at {SIGNIFICANCE:.0%}: {numbers}"
        )
    return (
        f"{head}no significant trend of merge time with b_type at {SIGNIFICANCE:.0%} "
        f"(sign: {row['direction']}): {numbers}"
    )


def _round(value: object, digits: int) -> float:
    x = float(value)  # type: ignore[arg-type]
    return round(x, digits) if math.isfinite(x) else math.nan
