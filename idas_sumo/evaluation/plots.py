"""PNG plots of an evaluation directory, after the paper's Fig. 4 (bars), Fig. 5 (position-time and
velocity profiles, merging zone shaded) and Fig. 6 (driver-type sweep), and of its flow.csv (ours).
A training run directory's learning curves are training/plots.py's (``idas-sumo plot`` picks by the files)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from idas_sumo.env.drawing import ZONE_COLOUR as ZONE_COLOR
from idas_sumo.env.rewards import MERGE_ZONE_RADIUS_M
from idas_sumo.errors import InputError
from idas_sumo.evaluation.metrics import (
    BASE_EPISODE_COLUMNS,
    EPISODE_COLUMNS,
    FLOW_COLUMNS,
    TRAJECTORY_COLUMNS,
)
from idas_sumo.evaluation.policies import METHOD_LABELS
from idas_sumo.evaluation.sweep import is_sweep_scenario, spearman_test
from idas_sumo.io_utils import OutputFolder, read_csv_columns, save_png

NUMBER_COLUMNS = frozenset({*EPISODE_COLUMNS, *FLOW_COLUMNS, *TRAJECTORY_COLUMNS}) - {
    "scenario",
    "method",
    "ego_id",
    "ego_road",
    "vehicle",
    "controlled",
    "road",
    "action",
    "allowed_actions",
}
"""The columns of evaluate's CSVs that hold numbers (the others hold names, flags and action lists)."""


def _read(path: Path, columns: tuple[str, ...]) -> pd.DataFrame:
    frame: pd.DataFrame = read_csv_columns(path, columns, "idas-sumo evaluate")
    for column in frame.columns:
        if column in NUMBER_COLUMNS:
            frame[column] = numbers(frame[column], path)
    return frame


def numbers(values: pd.Series, path: Path) -> pd.Series:
    """A CSV column the plots compute with, as numbers (empty cells: NaN); text in it is one InputError naming
    the file, the column and the first such row, not a traceback deep in pandas or matplotlib."""
    if pd.api.types.is_numeric_dtype(values):
        return values
    parsed = pd.to_numeric(values, errors="coerce")
    bad = parsed.isna() & values.notna()
    if bad.any():
        row = int(bad.to_numpy().argmax())
        raise InputError(
            f"{path}: column {values.name!r} holds {values.iloc[row]!r} in row {row + 1}, expected a number"
        )
    return parsed


def _label(method: object) -> str:
    return METHOD_LABELS.get(str(method), str(method))


def plot_directory(directory: Path) -> list[Path]:
    """Draw every plot the CSVs in ``directory`` support; returns the PNG paths."""
    import matplotlib

    matplotlib.use("Agg")
    if not directory.is_dir():
        raise InputError(f"{directory}: not a directory written by `idas-sumo evaluate` or `train`")
    if not (directory / "episodes.csv").exists():
        raise InputError(
            f"{directory}: no episodes.csv (run `idas-sumo evaluate --out {directory}` first) "
            "and no metrics.csv (not a training run either)"
        )
    # Locked as evaluate locks it, and each PNG recorded as the tool's (so `evaluate --force` clears it).
    with OutputFolder.open(directory, "plot"):
        return _plot_evaluation(directory)


def _plot_evaluation(directory: Path) -> list[Path]:
    """Every CSV the plots use is read and checked before the first PNG is written: a bad flow.csv
    leaves no summary.png behind (nor replaces an earlier one)."""
    # The columns of every episodes.csv ever written: older directories plot too.
    episodes = _read(directory / "episodes.csv", BASE_EPISODE_COLUMNS)
    flow_path, traj_path = directory / "flow.csv", directory / "trajectories.csv"
    flow = _read(flow_path, FLOW_COLUMNS) if flow_path.exists() else None
    names = episodes["scenario"].astype(str)
    representative = bool(names.isin(["s1", "s2", "s3", "s4"]).any())
    sweep = bool(names.map(is_sweep_scenario).any())
    traj = None
    if traj_path.exists() and (representative or sweep):
        traj = _read(traj_path, ("scenario", "run_method", *TRAJECTORY_COLUMNS))
    written = [summary_bars(episodes, directory / "summary.png")]
    if flow is not None:
        written.append(flow_plots(flow, episodes, directory / "flow.png"))
    if representative:
        written.append(representative_bars(episodes, directory / "representative.png"))
    if traj is not None:
        if representative:
            written.append(profiles(traj, directory / "profiles.png"))
        if sweep:
            written.append(driver_type_sweep(episodes, traj, directory / "driver_types.png"))
    return written


def summary_bars(episodes: pd.DataFrame, path: Path) -> Path:
    import matplotlib.pyplot as plt

    grouped = episodes.groupby("method", sort=False)
    methods = list(grouped.groups)
    success = grouped["success"].mean().to_numpy() * 100
    perfect = grouped["perfect"].mean().to_numpy() * 100
    x = np.arange(len(methods))
    fig, ax = plt.subplots(figsize=(1.6 * len(methods) + 2, 3.5))
    ax.bar(x - 0.2, success, 0.4, label="success", color="#3182bd")
    ax.bar(x + 0.2, perfect, 0.4, label="perfect success", color="#9ecae1")
    ax.set_xticks(x, [_label(m) for m in methods])
    ax.set_ylabel("scenarios, %")
    ax.set_ylim(0, 105)
    ax.set_title(f"Overall performance ({len(episodes) // max(len(methods), 1)} scenarios per method)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0))  # outside: no bar is ever hidden
    return save_png(fig, path)


def flow_plots(flow: pd.DataFrame, episodes: pd.DataFrame, path: Path) -> Path:
    """Per method, over its scenarios: throughput past the merge point, mean speed of every car, and
    hard brakes in the merging zone (from episodes.csv: flow.csv counts every hard brake)."""
    import matplotlib.pyplot as plt

    zone = episodes[["scenario", "method", "hard_brakes_merge_zone"]].astype({"scenario": str, "method": str})
    flow = flow.astype({"scenario": str, "method": str}).merge(zone, on=["scenario", "method"], how="left")
    methods = list(dict.fromkeys(flow["method"]))
    panels = (
        ("throughput_veh_per_h", "Throughput past the merge point", "vehicles per hour"),
        ("mean_speed_mps", "Mean speed of every car", "speed, m/s"),
        (
            "hard_brakes_merge_zone",
            f"Hard brakes within {MERGE_ZONE_RADIUS_M:.0f} m of the merge point",
            "per episode",
        ),
    )
    fig, axes = plt.subplots(1, 3, figsize=(min(16.0, 6.0 + 1.9 * len(methods)), 4.6), layout="constrained")
    for ax, (column, title, unit) in zip(axes, panels, strict=True):
        data = [flow.loc[flow["method"] == m, column].dropna().to_numpy(dtype=float) for m in methods]
        x = np.arange(1, len(methods) + 1)
        ax.boxplot(
            data,
            positions=x,
            widths=0.55,
            patch_artist=True,
            boxprops={"facecolor": ZONE_COLOR, "alpha": 0.7},
            medianprops={"color": "black"},
            flierprops={"marker": ".", "markersize": 4},
        )
        means = [float(d.mean()) if len(d) else np.nan for d in data]
        ax.plot(x, means, "D", color="#d62728", markersize=6, label="mean", zorder=3)
        ax.set_xticks(x, [_label(m) for m in methods])
        ax.set_title(title, fontsize=10)
        ax.set_ylabel(unit)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8, loc="best")
    scenarios = len(flow) // max(len(methods), 1)
    fig.suptitle(f"Traffic flow per method ({scenarios} scenarios each; boxes: quartiles, whiskers: 1.5 IQR)")
    return save_png(fig, path)


def representative_bars(episodes: pd.DataFrame, path: Path) -> Path:
    """Normalised reward and ego finish time per scenario and method; collisions in grey."""
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    rep = episodes[episodes["scenario"].astype(str).isin(["s1", "s2", "s3", "s4"])]
    methods = list(dict.fromkeys(rep["method"]))
    scenarios = ["s1", "s2", "s3", "s4"]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), layout="constrained")
    width = 0.8 / max(len(methods), 1)
    for k, method in enumerate(methods):
        rows = rep[rep["method"] == method].set_index("scenario").reindex(scenarios)
        failed = rows["success"].fillna(0).to_numpy() == 0
        x = np.arange(len(scenarios)) + (k - (len(methods) - 1) / 2) * width
        for ax, col in zip(axes, ("normalized_reward", "ego_finish_time_s"), strict=True):
            values = rows[col].fillna(0).to_numpy()
            bars = ax.bar(x, values, width, color=f"C{k}")
            for bar, bad in zip(bars, failed, strict=True):
                # A failure has no finish time and often a zero reward: mark it where the bar would be.
                if bad:
                    bar.set_color("0.6")
                    ax.annotate(
                        "×",
                        (bar.get_x() + bar.get_width() / 2, 0.0),
                        ha="center",
                        va="bottom",
                        color="0.35",
                        fontsize=11,
                        fontweight="bold",
                    )
    axes[0].set_ylabel("normalised reward of the merge car")
    axes[1].set_ylabel("merge car finish time, s")
    for ax in axes:
        ax.set_xticks(range(len(scenarios)), scenarios)
    # Legend patches from the method colours: a method whose first bar failed would otherwise show grey.
    handles = [Patch(color=f"C{k}", label=_label(m)) for k, m in enumerate(methods)]
    fig.legend(handles=handles, loc="outside lower center", ncol=len(methods), fontsize=8)
    fig.suptitle("Representative scenarios (grey ×: failure)")
    return save_png(fig, path)


def profiles(traj: pd.DataFrame, path: Path) -> Path:
    """Position-time and velocity profiles of s1-s4 for each method, merging zone shaded."""
    import matplotlib.pyplot as plt

    traj = traj[traj["scenario"].astype(str).isin(["s1", "s2", "s3", "s4"])]
    methods = list(dict.fromkeys(traj["run_method"]))
    fig, axes = plt.subplots(
        2 * len(methods), 4, figsize=(14, 4.2 * len(methods)), squeeze=False, layout="constrained"
    )
    for m, method in enumerate(methods):
        for s, name in enumerate(["s1", "s2", "s3", "s4"]):
            run = traj[(traj["run_method"] == method) & (traj["scenario"] == name)]
            pos_ax, vel_ax = axes[2 * m, s], axes[2 * m + 1, s]
            pos_ax.axhspan(-MERGE_ZONE_RADIUS_M, MERGE_ZONE_RADIUS_M, color=ZONE_COLOR, alpha=0.5, lw=0)
            for vehicle, rows in run.groupby("vehicle"):
                label = f"{vehicle}"
                pos_ax.plot(rows["time_s"], -rows["dist_to_merge_m"], label=label)
                vel_ax.plot(rows["time_s"], rows["speed_mps"], label=label)
            pos_ax.set_title(f"{_label(method)}: {name}")
            pos_ax.set_ylabel("position rel. to merge point, m")
            vel_ax.set_ylabel("speed, m/s")
            vel_ax.set_xlabel("time, s")
            pos_ax.legend(fontsize=7)
    fig.suptitle("Representative scenarios: position-time (merging zone shaded) and velocity profiles")
    return save_png(fig, path)


def driver_type_sweep(episodes: pd.DataFrame, traj: pd.DataFrame, path: Path) -> Path:
    """Merge car's merge time against its driver type (mean and standard deviation over the start
    offsets, Spearman's rho and p in the legend), and its velocity profiles at the first start offset
    (paper Fig. 6)."""
    import matplotlib.pyplot as plt

    sweep = episodes[episodes["scenario"].astype(str).map(is_sweep_scenario)]
    # Directories written before issue #15 have no merge time: their finish time stands in.
    time_col = "ego_merge_time_s" if "ego_merge_time_s" in sweep.columns else "ego_finish_time_s"
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 3.8))
    # Methods often tie exactly; shrinking markers and varied dashes keep every tied line visible.
    styles = [("o", 10, "-"), ("s", 7, "--"), ("^", 6, ":"), ("D", 4, "-."), ("x", 6, "-")]
    for k, (method, rows) in enumerate(sweep.groupby("method", sort=False)):
        marker, size, line = styles[k % len(styles)]
        stats = rows.groupby("ego_type")[time_col].agg(["mean", "std"]).fillna({"std": 0.0})
        valid = rows.dropna(subset=[time_col])
        rho, p = spearman_test(valid["ego_type"], valid[time_col])
        trend = f" (ρ = {rho:+.2f}, p = {p:.3f})" if np.isfinite(rho) else " (ρ undefined)"
        left.errorbar(
            stats.index,
            stats["mean"],
            yerr=stats["std"],
            marker=marker,
            markersize=size,
            linestyle=line,
            capsize=3,
            markerfacecolor="none" if k % 2 == 0 else None,
            label=_label(method) + trend,
        )
    left.set_xlabel("merge car driver type $b_{type}$")
    what = "merge time (from its entry)" if time_col == "ego_merge_time_s" else "finish time"
    left.set_ylabel(f"merge car {what}, s")
    left.legend(fontsize=8)
    cmap = plt.get_cmap("viridis")
    first_method = sweep["method"].iloc[0] if len(sweep) else None
    first_start = str(sweep["scenario"].iloc[0]).rsplit("-btype", 1)[0] if len(sweep) else ""
    shown = sweep[
        (sweep["method"] == first_method)
        & sweep["scenario"].astype(str).str.startswith(first_start + "-btype")
    ]
    speeds = []
    for _, row in shown.iterrows():
        run = traj[(traj["scenario"] == row["scenario"]) & (traj["run_method"] == first_method)]
        ego = run[run["vehicle"] == row["ego_id"]]
        color = cmap((row["ego_type"] + 2.0) / 4.0)
        right.plot(ego["time_s"], ego["speed_mps"], color=color, label=f"{row['ego_type']:+.1f}")
        speeds.append(ego["speed_mps"].to_numpy())
    if len(speeds) > 1 and all(len(v) == len(speeds[0]) and np.allclose(v, speeds[0]) for v in speeds):
        # Otherwise only the last colour shows and the figure looks like a single run.
        right.text(0.03, 0.95, "all profiles coincide", transform=right.transAxes, va="top", fontsize=9)
    right.set_xlabel("time, s")
    right.set_ylabel("merge car speed, m/s")
    right.set_title(f"{_label(first_method)}: velocity by driver type ({first_start})")
    right.legend(fontsize=7, ncol=3, title="$b_{type}$")
    return save_png(fig, path)
