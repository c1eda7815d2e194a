"""The training metrics sink: one CSV row per episode, TensorBoard scalars when it is installed."""

from __future__ import annotations

import csv
import logging
from pathlib import Path
from types import TracebackType
from typing import Any

from idas_sumo.errors import InputError
from idas_sumo.io_utils import atomic_open, record_output

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
    below it (rows written after the checkpoint, and a last row cut short); ``kept`` then holds the rows
    that stayed. A file that is not such a sink's (another header, a damaged row) is one InputError
    and is left as it was. Without it (a new run) the file starts empty.
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
        resume = keep_below_global_episode is not None
        if keep_below_global_episode is not None and self.path.exists():
            self._truncate(keep_below_global_episode)
        new = not resume or not self.path.exists() or self.path.stat().st_size == 0
        record_output(self.path)
        self._file = self.path.open("a" if resume else "w", newline="", encoding="utf-8")
        self._writer = csv.DictWriter(self._file, fieldnames=columns)
        if new:
            self._writer.writeheader()
            self._file.flush()
        self._tb: Any = None
        if tensorboard_keys:
            self._tb = _summary_writer(out_dir / TENSORBOARD_DIR)

    def _truncate(self, keep_below: int) -> None:
        rows = [row for row in read_rows(self.path, self.columns) if int(row["global_episode"]) < keep_below]
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


def _summary_writer(folder: Path) -> Any:
    """A TensorBoard SummaryWriter into ``folder`` (None when TensorBoard is not installed); the event
    file it creates is recorded as the tool's own, so ``--force`` removes it and nothing else there."""
    before = set(folder.iterdir()) if folder.is_dir() else set()
    try:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(log_dir=str(folder))
    except Exception:  # tensorboard not installed: CSV only
        return None
    for path in set(folder.iterdir()) - before:
        record_output(path)
    return writer


def read_rows(path: Path, columns: tuple[str, ...]) -> list[dict[str, str]]:
    """The complete rows of a sink's CSV, checked: the header must be ``columns`` and every row whole,
    with an integer ``global_episode``; only a last line without its newline (a write cut short by a
    crash or Ctrl-C) is dropped. Anything else is one InputError naming the file and the line."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: cannot read it ({err}); nothing was changed") from None
    lines = text.splitlines()
    if lines and not text.endswith("\n"):
        lines.pop()  # cut short mid-row
    reader = csv.reader(lines)
    header = next(reader, None)
    if header is not None and tuple(header) != columns:
        raise InputError(
            f"{path}: not written by `idas-sumo train` (its header is not the {len(columns)} columns "
            f"{columns[0]},...,{columns[-1]}); nothing was changed: move it away or choose another --out"
        )
    rows = []
    for line_no, values in enumerate(reader, 2):
        if len(values) != len(columns) or not values[columns.index("global_episode")].isdigit():
            raise InputError(
                f"{path}: line {line_no} is not a row `idas-sumo train` writes ({len(values)} values, "
                f"expected {len(columns)} with an integer global_episode); nothing was changed"
            )
        rows.append(dict(zip(columns, values, strict=True)))
    return rows


def _fmt(value: Any) -> Any:
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, float):
        return f"{value:.6g}"
    return value
