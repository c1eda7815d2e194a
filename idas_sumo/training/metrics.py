"""The training metrics sink: one CSV row per episode, TensorBoard scalars when it is installed."""

from __future__ import annotations

import csv
import logging
from pathlib import Path
from types import TracebackType
from typing import Any

from idas_sumo.io_utils import atomic_open

log = logging.getLogger(__name__)

__all__ = ["METRICS_NAME", "METRIC_COLUMNS", "TENSORBOARD_DIR", "MetricsSink"]

METRICS_NAME = "metrics.csv"
TENSORBOARD_DIR = "tensorboard"
"""The run directory's TensorBoard folder (when TensorBoard is installed)."""

METRIC_COLUMNS: tuple[str, ...] = (
    "stage",
    "episode",
    "global_episode",
    "agents",
    "return_mean",
    "finish",
    "collide",
    "impede",
    "flow",
    "success",
    "perfect",
    "collisions",
    "timed_out",
    "length_steps",
    "agent_steps",
    "sim_time_s",
    "actor_loss",
    "v_loss",
    "q_loss",
    "entropy",
    "wall_time_s",
)
TENSORBOARD_KEYS: tuple[str, ...] = (
    "return_mean",
    "success",
    "perfect",
    "actor_loss",
    "v_loss",
    "q_loss",
    "entropy",
)


class MetricsSink:
    """Appends rows to ``metrics.csv`` (or ``name`` with ``columns``). ``tensorboard_keys`` go to
    TensorBoard too when it is installed.

    On resume, ``keep_below_global_episode`` first drops every row whose ``global_episode`` is not
    below it (rows written after the checkpoint, and a row cut short); ``kept`` then holds the rows
    that stayed.
    """

    def __init__(
        self,
        out_dir: Path,
        keep_below_global_episode: int | None = None,
        name: str = METRICS_NAME,
        columns: tuple[str, ...] = METRIC_COLUMNS,
        tensorboard_keys: tuple[str, ...] = TENSORBOARD_KEYS,
    ) -> None:
        self.path = out_dir / name
        self.columns = columns
        self.tensorboard_keys = tensorboard_keys
        self.kept: list[dict[str, str]] = []
        if keep_below_global_episode is not None and self.path.exists():
            self._truncate(keep_below_global_episode)
        new = not self.path.exists() or self.path.stat().st_size == 0
        self._file = self.path.open("a", newline="", encoding="utf-8")
        self._writer = csv.DictWriter(self._file, fieldnames=columns)
        if new:
            self._writer.writeheader()
            self._file.flush()
        self._tb: Any = None
        if tensorboard_keys:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self._tb = SummaryWriter(log_dir=str(out_dir / TENSORBOARD_DIR))
            except Exception:  # tensorboard not installed: CSV only
                self._tb = None

    def _truncate(self, keep_below: int) -> None:
        with self.path.open(newline="", encoding="utf-8") as f:
            rows = []
            for row in csv.DictReader(f):
                episode = _episode_of(row, self.columns)
                if episode is not None and episode < keep_below:
                    rows.append(row)
        with atomic_open(self.path, "w", newline="", encoding="utf-8") as f:
            w = csv.DictWriter(f, fieldnames=self.columns)
            w.writeheader()
            w.writerows(rows)
        self.kept = rows

    def write(self, rows: list[dict[str, Any]]) -> None:
        for row in rows:
            self._writer.writerow({k: _fmt(row[k]) for k in self.columns})
            if self._tb is not None:
                step = int(row["global_episode"])
                for key in self.tensorboard_keys:
                    self._tb.add_scalar(f"{row['stage']}/{key}", float(row[key]), step)
        self._file.flush()

    def close(self) -> None:
        self._file.close()
        if self._tb is not None:
            self._tb.close()

    def __enter__(self) -> MetricsSink:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def _episode_of(row: dict[str, Any], columns: tuple[str, ...]) -> int | None:
    """The row's global episode, or None for a row cut short (a crash or Ctrl-C mid-write)."""
    if None in row or any(row.get(k) is None for k in columns):
        return None
    try:
        return int(row["global_episode"])
    except ValueError:
        return None


def _fmt(value: Any) -> Any:
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, float):
        return f"{value:.6g}"
    return value
