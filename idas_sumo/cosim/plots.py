"""``flows.png``: a co-simulation study's throughput, delay and hard brakes against demand, per penetration."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from idas_sumo.io_utils import read_csv_columns, save_png

PANELS = (
    ("throughput_veh_per_h", "throughput past the merge (veh/h)"),
    ("mean_time_loss_s", "mean time loss per car (s)"),
    ("hard_brakes_per_1000_veh_km", "hard brakes per 1,000 veh-km"),
)
GROUP = ("net", "junction", "policy", "safety_mask", "penetration")


def plot_flows(flows_csv: Path, out: Path) -> Path:
    """One panel per statistic (``PANELS``) against the total demand, one line per penetration (and net,
    policy, mask where the study has several): the mean over seeds, the bars their range."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = (*GROUP, "demand_main_veh_per_h", "demand_merge_veh_per_h", "seed", *(c for c, _ in PANELS))
    frame = read_csv_columns(flows_csv, cols, "idas-sumo cosim")
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


__all__ = ["plot_flows"]
