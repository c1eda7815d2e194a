"""Episode and flow statistics computed from one episode's per-step trajectory (pure functions).

Definitions (docs/design-notes.md, "Definitions"; ours where the paper is silent): *success* = no collision and every
controlled vehicle finished in time; *perfect* = success and no reward deduction for any agent (no
impede, no flow penalty); throughput = vehicles past the merge point per hour of simulated time.
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
EPISODE_COLUMNS: tuple[str, ...] = (
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
SUMMARY_COLUMNS: tuple[str, ...] = (
    "method",
    "scenarios",
    "success_pct",
    "perfect_pct",
    "avg_speed_perfect_mps",
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


def merge_crossings(trajectory: pd.DataFrame) -> pd.Series:
    """Per vehicle, the first time its front is at or past the merge point (NaN if never)."""
    past = trajectory[trajectory["dist_to_merge_m"] <= 0.0]
    crossed = past.groupby("vehicle")["time_s"].min()
    return crossed.reindex(trajectory["vehicle"].unique())


def finish_times(trajectory: pd.DataFrame) -> pd.Series:
    """Per vehicle, the first time it is FINISH_DISTANCE_PAST_MERGE_M past the merge point."""
    done = trajectory[trajectory["dist_to_merge_m"] <= -FINISH_DISTANCE_PAST_MERGE_M]
    return done.groupby("vehicle")["time_s"].min().reindex(trajectory["vehicle"].unique())


def episode_row(trajectory: pd.DataFrame, facts: EpisodeFacts) -> dict[str, object]:
    controlled = trajectory[trajectory["controlled"]]
    ego = trajectory[trajectory["vehicle"] == facts.ego_id]
    success = is_success(facts.collisions, facts.all_finished)
    perfect = is_perfect(success, facts.impedes, facts.hard_brakes_merge_zone)
    ego_finish = finish_times(ego).get(facts.ego_id, np.nan)
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
        "ego_finish_time_s": round(float(ego_finish - facts.start_time_s), 3)
        if np.isfinite(ego_finish)
        else np.nan,
        "ego_mean_speed_mps": round(float(ego["speed_mps"].mean()), 4),
        "mean_speed_mps": round(float(controlled["speed_mps"].mean()), 4),
        "total_reward": round(facts.ego_total_reward, 4),
        "normalized_reward": round(facts.ego_total_reward / float(finish_reward(facts.ego_type)), 4),
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


def summary_rows(episodes: pd.DataFrame) -> list[dict[str, object]]:
    """The paper's table: one row per method."""
    rows: list[dict[str, object]] = []
    for method, group in episodes.groupby("method", sort=False):
        perfect = group[group["perfect"] == 1]
        rows.append(
            {
                "method": method,
                "scenarios": len(group),
                "success_pct": round(100.0 * group["success"].mean(), 2),
                "perfect_pct": round(100.0 * group["perfect"].mean(), 2),
                "avg_speed_perfect_mps": round(float(perfect["mean_speed_mps"].mean()), 3)
                if len(perfect)
                else np.nan,
            }
        )
    return rows
