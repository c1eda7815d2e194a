"""Learning curves of a training run directory (``idas-sumo plot RUN_DIR``): from ``metrics.csv`` (one
row per training episode) and ``validation.csv`` (one row per validation), stage boundaries marked."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd

from idas_sumo.env.rewards import FLOW_PENALTY_PER_HARD_BRAKE
from idas_sumo.errors import InputError
from idas_sumo.io_utils import read_csv_columns, save_png
from idas_sumo.training.metrics import METRICS_NAME
from idas_sumo.training.validation import VALIDATION_COLUMNS, VALIDATION_NAME

LEARNING_CURVES_NAME = "learning_curves.png"
METRICS_NEEDED: tuple[str, ...] = (
    "stage",
    "global_episode",
    "return_mean",
    "flow",
    "success",
    "perfect",
    "collisions",
)
"""The metrics.csv columns the curves read."""
CURVE_POINTS = 60
"""About this many rolling windows per stage: a window of len(stage) / CURVE_POINTS episodes smooths
the episode-to-episode noise (one episode's success is 0 or 1) without hiding a collapse."""
SUCCESS_COLOUR, PERFECT_COLOUR, COLLISION_COLOUR, LINE_COLOUR = "#2ca02c", "#1f77b4", "#d62728", "0.2"
"""One colour per quantity in every panel (stages are told apart by the dashed boundary)."""


ROLLING_PERCENT, HELD_OUT_PERCENT = "episodes, % (rolling mean)", "held-out scenarios, %"
JOINT_RETURN_LABEL, ENTROPY_TITLE = "mean joint return per episode", "Actor entropy (one value per update)"


def _panel(ax: Any, title: str, ylabel: str, percent: bool = False) -> None:
    """A panel's title and y label; a percentage's axis from 0 to 100 with a margin."""
    ax.set_title(title, fontsize=10)
    ax.set_ylabel(ylabel)
    if percent:
        ax.set_ylim(-3, 103)


def is_training_run(directory: Path) -> bool:
    """A directory written by ``idas-sumo train`` (it has metrics.csv or validation.csv)."""
    return (directory / METRICS_NAME).is_file() or (directory / VALIDATION_NAME).is_file()


def _read(path: Path, columns: tuple[str, ...]) -> pd.DataFrame:
    """``path`` with ``columns``; each of them but ``stage`` holds numbers (text in one is an InputError that
    names the file, the column and the row, not a traceback in pandas)."""
    frame: pd.DataFrame = read_csv_columns(path, columns, "idas-sumo train")
    for column in columns:
        values = frame[column]
        if column == "stage" or pd.api.types.is_numeric_dtype(values):
            continue
        parsed = pd.to_numeric(values, errors="coerce")
        bad = (parsed.isna() & values.notna()).to_numpy()
        if bad.any():
            row = int(bad.argmax())
            raise InputError(
                f"{path}: column {column!r} holds {values.iloc[row]!r} in row {row + 1}, expected a number"
            )
        frame[column] = parsed
    return frame


def _rolling(values: pd.Series, window: int) -> pd.Series:
    return values.rolling(window, min_periods=max(1, window // 2)).mean()


def plot_training_run(directory: Path) -> list[Path]:
    """Draw the learning curves of a training run into ``directory``; returns the PNG paths."""
    import matplotlib

    matplotlib.use("Agg")
    metrics, validation = _read_run(directory, METRICS_NEEDED)
    return [learning_curves(metrics, validation, directory / LEARNING_CURVES_NAME, directory.name)]


def _read_run(
    directory: Path, metrics_columns: tuple[str, ...]
) -> tuple[pd.DataFrame | None, pd.DataFrame | None]:
    """A run's metrics.csv (with ``metrics_columns``) and validation.csv, None where the file is absent; a run
    with no rows in either is an InputError."""
    metrics_path, validation_path = directory / METRICS_NAME, directory / VALIDATION_NAME
    metrics = _read(metrics_path, metrics_columns) if metrics_path.is_file() else None
    validation = _read(validation_path, VALIDATION_COLUMNS) if validation_path.is_file() else None
    if (metrics is None or metrics.empty) and (validation is None or validation.empty):
        raise InputError(f"{directory}: its {METRICS_NAME} and {VALIDATION_NAME} hold no rows yet")
    return metrics, validation


def learning_curves(
    metrics: pd.DataFrame | None, validation: pd.DataFrame | None, path: Path, title: str
) -> Path:
    """Six panels over the run's global episode: return; success, perfect and collision rates; hard
    brakes in the merging zone (rolling means within each stage); validation's joint return (the
    stage's best weights starred) and its success and perfect rates; the actor's entropy. A dashed
    line and the stage's name where a stage begins."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(15, 7.5), layout="constrained", sharex=True)
    (ret_ax, rate_ax, brake_ax), (vret_ax, vrate_ax, ent_ax) = axes
    starts: dict[str, int] = {}
    windows: dict[str, int] = {}
    if metrics is not None and len(metrics):
        metrics = metrics.sort_values("global_episode", kind="stable")
        for stage in dict.fromkeys(metrics["stage"].astype(str)):
            rows = metrics[metrics["stage"].astype(str) == stage]
            starts[stage] = int(rows["global_episode"].iloc[0])
            windows[stage] = max(1, len(rows) // CURVE_POINTS)
            # One legend entry per quantity, not per stage.
            _training_stage(axes, rows, windows[stage], first=len(starts) == 1)
    smoothing = ", ".join(f"{stage} {w}" for stage, w in windows.items())
    _panel(ret_ax, "Training: mean return per agent", "return (rolling mean)")
    _panel(
        rate_ax,
        "Training: episodes with success, perfect success, a collision",
        ROLLING_PERCENT,
        percent=True,
    )
    _panel(brake_ax, "Training: hard brakes in the merging zone", "per episode (rolling mean)")
    _panel(ent_ax, ENTROPY_TITLE, "entropy, nats")

    if validation is not None and len(validation):
        for stage in dict.fromkeys(validation["stage"].astype(str)):
            rows = validation[validation["stage"].astype(str) == stage]
            starts.setdefault(stage, int(rows["global_episode"].iloc[0]))
            _validation_stage(vret_ax, vrate_ax, rows, first=stage == validation["stage"].astype(str).iloc[0])
        vret_ax.set_title("Validation: joint return on held-out scenarios", fontsize=10)
    else:
        vret_ax.set_title("Validation: none in this run", fontsize=10)
    vret_ax.set_ylabel(JOINT_RETURN_LABEL)
    _panel(vrate_ax, "Validation: success and perfect success", HELD_OUT_PERCENT, percent=True)

    _mark_stages(axes, starts)
    for ax in axes[1]:
        ax.set_xlabel("training episode (all stages)")
    suffix = f" (rolling means over {smoothing} episodes)" if smoothing else ""
    fig.suptitle(f"Learning curves: {title}{suffix}; dashed: a new stage begins")
    return save_png(fig, path)


def _training_stage(axes: Any, rows: pd.DataFrame, window: int, first: bool) -> None:
    """One stage's metrics.csv rows on the training panels (rolling means over ``window`` episodes);
    ``first`` labels the lines for the legend."""
    (ret_ax, rate_ax, brake_ax), (_, _, ent_ax) = axes
    x = rows["global_episode"]
    ret_ax.plot(x, _rolling(rows["return_mean"], window), color=LINE_COLOUR)
    # Success drawn wider beneath perfect success: where they are equal, both stay visible.
    for column, colour, width, name in (
        ("success", SUCCESS_COLOUR, 3.0, "success"),
        ("perfect", PERFECT_COLOUR, 1.3, "perfect success"),
    ):
        rate_ax.plot(
            x,
            100 * _rolling(rows[column], window),
            color=colour,
            lw=width,
            label=name if first else None,
        )
    crashed = (rows["collisions"] > 0).astype(float)
    rate_ax.plot(
        x,
        100 * _rolling(crashed, window),
        color=COLLISION_COLOUR,
        label="collision" if first else None,
    )
    zone_brakes = rows["flow"] / FLOW_PENALTY_PER_HARD_BRAKE  # r_flow is -1 per merge-zone brake
    brake_ax.plot(x, _rolling(zone_brakes, window), color=LINE_COLOUR)
    if "entropy" in rows.columns:
        ent_ax.plot(x, rows["entropy"], color=LINE_COLOUR, lw=0.8)


def _validation_stage(vret_ax: Any, vrate_ax: Any, rows: pd.DataFrame, first: bool) -> None:
    """One stage's validation.csv rows: joint return (its best weights starred) and the success rates."""
    x = rows["global_episode"]
    vret_ax.plot(x, rows["joint_return"], marker="o", ms=3, color=LINE_COLOUR)
    for column, colour, width, marker, name in (
        ("success_rate", SUCCESS_COLOUR, 3.0, "o", "success"),
        ("perfect_rate", PERFECT_COLOUR, 1.3, "s", "perfect success"),
    ):
        vrate_ax.plot(
            x,
            100 * rows[column],
            marker=marker,
            ms=2 * width + 1,
            lw=width,
            color=colour,
            label=name if first else None,
        )
    best = rows[rows["best"] == 1]
    if len(best):  # the stage's last new best is its <stage>_best.pt
        b = best.iloc[-1]
        vret_ax.plot(
            b["global_episode"],
            b["joint_return"],
            marker="*",
            ms=15,
            color="gold",
            mec="black",
            ls="",
            label="best weights (<stage>_best.pt)" if not vret_ax.get_legend_handles_labels()[0] else None,
        )


def _mark_stages(axes: Any, starts: dict[str, int]) -> None:
    """Every panel: a grid, a dashed line where a stage begins after the first, each stage's name, a legend
    where there are labelled lines."""
    ordered = sorted(starts.items(), key=lambda kv: kv[1])
    for ax in axes.flat:
        ax.grid(alpha=0.25)
        for k, (stage, start) in enumerate(ordered):
            if k:
                ax.axvline(start, color="0.45", ls="--", lw=0.9)
            ax.annotate(
                stage,
                (start, 1.0),
                xycoords=("data", "axes fraction"),
                xytext=(3, -11),
                textcoords="offset points",
                fontsize=8,
                color="0.4",
                annotation_clip=True,
            )
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8, loc="best")


COMPARE_METRICS: tuple[str, ...] = ("global_episode", "collisions", "timed_out")
"""The metrics.csv columns the comparison of runs reads (entropy too, where the run has it)."""


def compare_runs(directories: list[Path], path: Path) -> Path:
    """Several training runs (seeds, variants) on one figure, one colour each: validation success and joint
    return (each run's best starred), and the training episodes with a collision or a timeout (rolling
    means) and the actor's entropy, over each run's global episode. The spread across seeds, at a glance."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = []
    for directory in directories:
        if not is_training_run(directory):
            raise InputError(f"{directory}: not a training run (no {METRICS_NAME} or {VALIDATION_NAME})")
        runs.append((directory.name, *_read_run(directory, COMPARE_METRICS)))

    fig, axes = plt.subplots(2, 2, figsize=(13, 7.5), layout="constrained", sharex=True)
    (vrate_ax, vret_ax), (fail_ax, ent_ax) = axes
    for k, (name, metrics, validation) in enumerate(runs):
        colour = f"C{k % 10}"
        if validation is not None and len(validation):
            x = validation["global_episode"]
            vrate_ax.plot(x, 100 * validation["success_rate"], color=colour, lw=1.2, label=name)
            vret_ax.plot(x, validation["joint_return"], color=colour, lw=1.2, label=name)
            flagged = validation[validation["best"] == 1]
            if len(flagged):  # the last new best is the run's <stage>_best.pt
                best = flagged.iloc[-1]
                vret_ax.plot(
                    best["global_episode"], best["joint_return"], marker="*", ms=14, color=colour, mec="black"
                )
        if metrics is not None and len(metrics):
            metrics = metrics.sort_values("global_episode", kind="stable")
            window = max(1, len(metrics) // CURVE_POINTS)
            x = metrics["global_episode"]
            fail_ax.plot(
                x,
                100 * _rolling((metrics["collisions"] > 0).astype(float), window),
                color=colour,
                label=f"{name}: collision",
            )
            fail_ax.plot(
                x,
                100 * _rolling(metrics["timed_out"].astype(float), window),
                color=colour,
                ls=":",
                label=f"{name}: timeout",
            )
            if "entropy" in metrics.columns:
                ent_ax.plot(x, metrics["entropy"], color=colour, lw=0.8, label=name)
    _panel(vrate_ax, "Validation: success on held-out scenarios", HELD_OUT_PERCENT, percent=True)
    _panel(vret_ax, "Validation: joint return (each run's best weights starred)", JOINT_RETURN_LABEL)
    _panel(
        fail_ax,
        "Training: episodes with a collision (solid) or a timeout (dotted)",
        ROLLING_PERCENT,
        percent=True,
    )
    _panel(ent_ax, ENTROPY_TITLE, "entropy, nats")
    for ax in axes.flat:
        ax.grid(alpha=0.25)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8, loc="best")
    for ax in axes[1]:
        ax.set_xlabel("training episode (all stages)")
    fig.suptitle(f"{len(runs)} training runs compared")
    return save_png(fig, path)
