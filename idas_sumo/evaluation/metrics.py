"""Episode and flow statistics computed from one episode's per-step trajectory (pure functions).

Definitions (docs/design-notes.md, "Definitions"; ours where the paper is silent): *success* = no collision and every
controlled vehicle finished in time; *perfect* = success and no reward deduction for any agent (no
impede, no flow penalty); *perfect without flow* = success and no impede (the flow penalty ignored);
*timeout* = the episode was cut off with some controlled car neither finished nor collided; *ego success* =
the method's own car finished (so did not collide), whatever the others did; throughput = vehicles past the
merge point per hour of simulated time. Success and perfect are env/engine.py's ``is_success`` and
``is_perfect``, the ones training and validation use.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from idas_sumo.env.engine import is_perfect, is_success
from idas_sumo.env.rewards import FINISH_DISTANCE_PAST_MERGE_M, finish_reward

TRAJECTORY_COLUMNS: tuple[str, ...] = (
    "time_s",
    "vehicle",
    "controlled",
    "method",
    "road",
    "dist_to_merge_m",
    "speed_mps",
    "accel_mps2",
    "action",
    "allowed_actions",
)
BASE_EPISODE_COLUMNS: tuple[str, ...] = (
    "scenario",
    "seed",
    "method",
    "ego_id",
    "ego_road",
    "ego_prio",
    "ego_type",
    "success",
    "perfect",
    "collisions",
    "hard_brakes",
    "hard_brakes_merge_zone",
    "ego_finish_time_s",
    "ego_mean_speed_mps",
    "mean_speed_mps",
    "total_reward",
    "normalized_reward",
)
"""The first columns of ``EPISODE_COLUMNS``, those of every episodes.csv ever written (plots need no more)."""
EPISODE_COLUMNS: tuple[str, ...] = (
    *BASE_EPISODE_COLUMNS,
    # Added for issue #15 (at the end, so that readers of the first columns keep working):
    "perfect_no_flow",
    "timeout",
    "ego_success",
    "ego_travel_time_s",
    "ego_merge_time_s",
    "ego_merge_speed_mps",
)
SUMMARY_COLUMNS: tuple[str, ...] = (
    "method",
    "scenarios",
    "success_pct",
    "perfect_pct",
    "avg_speed_perfect_mps",
    # Added for issue #15, at the end as above:
    "perfect_no_flow_pct",
    "collision_pct",
    "timeout_pct",
    "ego_success_pct",
)
FLOW_COLUMNS: tuple[str, ...] = (
    "scenario",
    "method",
    "vehicles",
    "throughput_veh_per_h",
    "mean_speed_mps",
    "mean_travel_time_s",
    "mean_time_loss_s",
    "hard_brakes",
    "merge_time_s",
)


@dataclass(frozen=True)
class EpisodeFacts:
    """What the protocol counted while the episode ran (beyond the trajectory)."""

    scenario: str
    seed: int
    method: str
    ego_id: str
    ego_road: str
    ego_prio: int
    ego_type: float
    collisions: int
    hard_brakes: int
    hard_brakes_merge_zone: int
    impedes: int
    all_finished: bool
    ego_total_reward: float
    duration_s: float
    start_time_s: float
    free_flow_time_s: dict[str, float]
    """Per vehicle: time to drive from its start to the finish line at its road's limit."""
    timed_out: bool = False
    """The episode was cut off at its time limit (``EpisodeOutcome.timed_out``)."""
    ego_end_reason: str = ""
    """How the ego's episode ended (``EpisodeOutcome.end_reasons``); empty if it never entered."""


def is_perfect_no_flow(success: bool, impedes: int) -> bool:
    """Perfect success with the flow penalty (hard brakes in the merging zone) ignored."""
    return is_perfect(success, impedes, hard_brakes_merge_zone=0)


def is_timeout(timed_out: bool, all_finished: bool) -> bool:
    """The time limit ended the episode before every controlled car finished (a car that collided
    also counts as not finished: a scenario can count as both a collision and a timeout)."""
    return timed_out and not all_finished


def is_ego_success(ego_end_reason: str) -> bool:
    """The method's own car finished (a car that collides ends 'collided'), whatever the others did."""
    return ego_end_reason == "finished"


def merge_crossings(trajectory: pd.DataFrame) -> pd.Series:
    """Per vehicle, the first time its front is at or past the merge point (NaN if never)."""
    past = trajectory[trajectory["dist_to_merge_m"] <= 0.0]
    crossed = past.groupby("vehicle")["time_s"].min()
    return crossed.reindex(trajectory["vehicle"].unique())


def finish_times(trajectory: pd.DataFrame) -> pd.Series:
    """Per vehicle, the first time it is FINISH_DISTANCE_PAST_MERGE_M past the merge point."""
    done = trajectory[trajectory["dist_to_merge_m"] <= -FINISH_DISTANCE_PAST_MERGE_M]
    return done.groupby("vehicle")["time_s"].min().reindex(trajectory["vehicle"].unique())


def entry_times(trajectory: pd.DataFrame) -> pd.Series:
    """Per vehicle, the first time it is on the road (cars enter at staggered times)."""
    return trajectory.groupby("vehicle")["time_s"].min().reindex(trajectory["vehicle"].unique())


def _seconds(value: float) -> float:
    return round(float(value), 3) if np.isfinite(value) else np.nan


def episode_row(trajectory: pd.DataFrame, facts: EpisodeFacts) -> dict[str, object]:
    controlled = trajectory[trajectory["controlled"]]
    ego = trajectory[trajectory["vehicle"] == facts.ego_id]
    success = is_success(facts.collisions, facts.all_finished)
    perfect = is_perfect(success, facts.impedes, facts.hard_brakes_merge_zone)
    ego_finish = finish_times(ego).get(facts.ego_id, np.nan)
    ego_entry = entry_times(ego).get(facts.ego_id, np.nan)
    ego_merge = merge_crossings(ego).get(facts.ego_id, np.nan)
    before_merge = ego[ego["time_s"] < ego_merge]  # empty (NaN speed) if it never got there
    return {
        "scenario": facts.scenario,
        "seed": facts.seed,
        "method": facts.method,
        "ego_id": facts.ego_id,
        "ego_road": facts.ego_road,
        "ego_prio": facts.ego_prio,
        "ego_type": facts.ego_type,
        "success": int(success),
        "perfect": int(perfect),
        "collisions": facts.collisions,
        "hard_brakes": facts.hard_brakes,
        "hard_brakes_merge_zone": facts.hard_brakes_merge_zone,
        # From the episode's start (kept for old readers); ego_travel_time_s is from the ego's entry.
        "ego_finish_time_s": _seconds(ego_finish - facts.start_time_s),
        "ego_mean_speed_mps": round(float(ego["speed_mps"].mean()), 4),
        "mean_speed_mps": round(float(controlled["speed_mps"].mean()), 4),
        "total_reward": round(facts.ego_total_reward, 4),
        "normalized_reward": round(facts.ego_total_reward / float(finish_reward(facts.ego_type)), 4),
        "perfect_no_flow": int(is_perfect_no_flow(success, facts.impedes)),
        "timeout": int(is_timeout(facts.timed_out, facts.all_finished)),
        "ego_success": int(is_ego_success(facts.ego_end_reason)),
        "ego_travel_time_s": _seconds(ego_finish - ego_entry),
        "ego_merge_time_s": _seconds(ego_merge - ego_entry),
        "ego_merge_speed_mps": round(float(before_merge["speed_mps"].mean()), 4)
        if len(before_merge)
        else np.nan,
    }


def flow_row(trajectory: pd.DataFrame, facts: EpisodeFacts) -> dict[str, object]:
    crossings = merge_crossings(trajectory).dropna()
    finishes = finish_times(trajectory).dropna()
    starts = trajectory.groupby("vehicle")["time_s"].min()
    travel = (finishes - starts.reindex(finishes.index)).astype(float)
    free = pd.Series(facts.free_flow_time_s).reindex(finishes.index).astype(float)
    merge_time = float(crossings.max() - crossings.min()) if len(crossings) else np.nan
    return {
        "scenario": facts.scenario,
        "method": facts.method,
        "vehicles": int(trajectory["vehicle"].nunique()),
        "throughput_veh_per_h": round(len(crossings) / facts.duration_s * 3600.0, 3),
        "mean_speed_mps": round(float(trajectory["speed_mps"].mean()), 4),
        "mean_travel_time_s": round(float(travel.mean()), 3) if len(travel) else np.nan,
        "mean_time_loss_s": round(float((travel - free).mean()), 3) if len(travel) else np.nan,
        "hard_brakes": facts.hard_brakes,
        "merge_time_s": round(merge_time, 3),
    }


def _pct(flags: pd.Series) -> float:
    return round(100.0 * float(flags.mean()), 2)


def summary_rows(episodes: pd.DataFrame) -> list[dict[str, object]]:
    """The paper's table, one row per method, and our further columns (the flags of ``episode_row``)."""
    rows: list[dict[str, object]] = []
    for method, group in episodes.groupby("method", sort=False):
        perfect = group[group["perfect"] == 1]
        rows.append(
            {
                "method": method,
                "scenarios": len(group),
                "success_pct": _pct(group["success"]),
                "perfect_pct": _pct(group["perfect"]),
                "avg_speed_perfect_mps": round(float(perfect["mean_speed_mps"].mean()), 3)
                if len(perfect)
                else np.nan,
                "perfect_no_flow_pct": _pct(group["perfect_no_flow"]),
                "collision_pct": _pct(group["collisions"] > 0),
                "timeout_pct": _pct(group["timeout"]),
                "ego_success_pct": _pct(group["ego_success"]),
            }
        )
    return rows


@dataclass(frozen=True)
class PairedMargin:
    """``method`` minus ``against`` on one 0/1 column, in percentage points, over the scenarios both ran."""

    margin_pts: float
    standard_error_pts: float
    scenarios: int


def paired_margin(episodes: pd.DataFrame, method: str, against: str, column: str = "perfect") -> PairedMargin:
    """The difference of two methods on the same scenarios (matched on seed and scenario: each scenario is the
    same for both, only the ego's method differs), with the standard error of the mean paired difference
    (sample standard deviation / √n). Pairing removes the scenario-to-scenario spread both methods share."""
    keys = ["seed", "scenario"]
    a = episodes[episodes["method"] == method].set_index(keys)[column]
    b = episodes[episodes["method"] == against].set_index(keys)[column]
    both = a.index.intersection(b.index)
    if len(both) < 2:
        raise ValueError(f"{method} and {against} share {len(both)} scenarios; a margin needs two or more")
    diff = (a.loc[both].astype(float) - b.loc[both].astype(float)).to_numpy()
    return PairedMargin(
        margin_pts=round(100.0 * float(diff.mean()), 2),
        standard_error_pts=round(100.0 * float(diff.std(ddof=1)) / float(np.sqrt(len(diff))), 2),
        scenarios=len(diff),
    )
