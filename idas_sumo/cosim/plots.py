"""A co-simulation study's plots: ``flows.png`` (throughput, delay and hard brakes against demand, per
penetration) and, for each run recorded with ``--trajectories``, a time-space diagram of the merge."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from idas_sumo.io_utils import read_csv_columns, save_png

PANELS = (
    ("throughput_veh_per_h", "throughput past the merge (veh/h)"),
    ("mean_time_loss_s", "mean time loss per car (s)"),
    ("hard_brakes_per_1000_veh_km", "hard brakes per 1,000 veh-km"),
)
GROUP = ("net", "junction", "demand_profile", "policy", "safety_mask", "penetration")
OPTIONAL = ("demand_profile",)
"""Group columns a flows.csv written before them lacks."""


def plot_flows(flows_csv: Path, out: Path) -> Path:
    """One panel per statistic (``PANELS``) against the total demand, one line per penetration (and net,
    policy, mask where the study has several): the mean over seeds, the bars their range."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    group = tuple(g for g in GROUP if g not in OPTIONAL)
    cols = (*group, "demand_main_veh_per_h", "demand_merge_veh_per_h", "seed", *(c for c, _ in PANELS))
    frame = read_csv_columns(flows_csv, cols, "idas-sumo cosim")
    for name in OPTIONAL:
        column = frame[name].astype(object) if name in frame.columns else None  # all empty: read as NaN
        frame[name] = "" if column is None else column.where(column.notna(), "").astype(str)
    frame["total_demand"] = frame["demand_main_veh_per_h"] + frame["demand_merge_veh_per_h"]
    varying = [g for g in GROUP if frame[g].nunique() > 1 or g == "penetration"]
    fig, axes = plt.subplots(1, len(PANELS), figsize=(5 * len(PANELS), 4))
    for key, group in frame.groupby(varying, sort=True):
        values = key if isinstance(key, tuple) else (key,)
        label = ", ".join(
            f"p = {v:g}" if g == "penetration" else str(v) for g, v in zip(varying, values, strict=True)
        )
        for ax, (column, _) in zip(axes, PANELS, strict=True):
            stats = group.groupby("total_demand")[column].agg(["mean", "min", "max"]).sort_index()
            x = stats.index.to_numpy(dtype=float)
            mean = stats["mean"].to_numpy(dtype=float)
            spread = [mean - stats["min"].to_numpy(dtype=float), stats["max"].to_numpy(dtype=float) - mean]
            err = np.clip(np.nan_to_num(np.vstack(spread)), 0.0, None)  # rounding can leave -1e-16
            ax.errorbar(x, mean, yerr=err, marker="o", capsize=3, label=label)
    for ax, (_, title) in zip(axes, PANELS, strict=True):
        ax.set_xlabel("demand, both roads (veh/h)")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    return save_png(fig, out)


TIME_SPACE_ROADS = ("main", "merge")
"""One panel per incoming road, each with the road after the merge point (where both roads' cars go)."""


def plot_time_space(trajectory_csv: Path, out: Path) -> Path:
    """Position along the road (m from the merge point; negative before it) against time, one panel per
    incoming road with the cars that came from it, coloured by speed; automated cars as triangles,
    SUMO-driven ones as dots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = ("time_s", "vehicle", "road", "position_m", "speed_mps", "automated")
    frame = read_csv_columns(trajectory_csv, cols, "idas-sumo cosim --trajectories")
    origin = frame["vehicle"].astype(str).str.partition(".")[0]
    vmax = max(float(frame["speed_mps"].max()), 1.0) if len(frame) else 1.0
    fig, axes = plt.subplots(len(TIME_SPACE_ROADS), 1, figsize=(11, 7), sharex=True)
    scatter = None
    for ax, road in zip(axes, TIME_SPACE_ROADS, strict=True):
        cars = frame[origin == road]
        for automated, marker, size, label in ((0, ".", 3, "SUMO-driven"), (1, "^", 6, "automated")):
            part = cars[cars["automated"] == automated]
            scatter = ax.scatter(
                part["time_s"],
                part["position_m"],
                c=part["speed_mps"],
                cmap="viridis_r",
                vmin=0,
                vmax=vmax,
                marker=marker,
                s=size,
                linewidths=0,
                label=f"{label} ({part['vehicle'].nunique()} cars)",
            )
        ax.axhline(0.0, color="k", lw=0.6, ls="--")
        ax.set_ylabel(f"{road} road: m past the merge point")
        ax.legend(loc="upper left", fontsize=8, markerscale=3)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time (s)")
    fig.suptitle(f"time-space diagram of the merge: {trajectory_csv.stem}", fontsize=10)
    if scatter is not None:
        fig.colorbar(scatter, ax=list(axes), label="speed (m/s)")
    return save_png(fig, out)


def plot_study(directory: Path, flows_name: str, plot_name: str, trajectory_dir: str) -> list[Path]:
    """Every plot a cosim folder supports: ``flows.png`` and a time-space diagram per trajectory file."""
    written = [plot_flows(directory / flows_name, directory / plot_name)]
    for csv in sorted((directory / trajectory_dir).glob("*.csv")):
        written.append(plot_time_space(csv, csv.with_suffix(".png")))
    return written


__all__ = ["plot_flows", "plot_study", "plot_time_space"]
