"""The grid of co-simulation runs behind ``idas-sumo cosim``: demand x penetration x seed, resumable.

Each finished run adds one row to ``flows.csv`` and one row per time bin to ``bins.csv`` (both rewritten
whole, atomically, after every run); ``flows.png`` (cosim/plots.py) is drawn from ``flows.csv`` at the end. A run is known by its key columns (``KEY_COLUMNS``): started again
in the same folder, the study skips every run whose key ``flows.csv`` already holds, so an interrupted
study resumes where it stopped, and a larger grid only runs what is new. SUMO's own output files of a
run live in a temporary folder while it runs.
"""

from __future__ import annotations

import csv
import math
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from idas_sumo.cosim.demand import demand_label
from idas_sumo.cosim.plots import plot_flows
from idas_sumo.cosim.run import RunResult, run_once
from idas_sumo.cosim.stats import Row
from idas_sumo.env.actions import DEFAULT_SAFETY_MASK, SafetyMask
from idas_sumo.env.contracts import Policy
from idas_sumo.errors import InputError
from idas_sumo.io_utils import atomic_open, output_directory
from idas_sumo.sim.flows import FlowDemand
from idas_sumo.sim.merge_detect import MergeSite, Side

FLOWS_NAME = "flows.csv"
BINS_NAME = "bins.csv"
PLOT_NAME = "flows.png"
KEY_COLUMNS = (
    "net",
    "junction",
    "demand",
    "demand_main_veh_per_h",
    "demand_merge_veh_per_h",
    "penetration",
    "policy",
    "safety_mask",
    "seed",
    "duration_s",
    "bin_s",
    "warmup_s",
)
"""What names a run; a row of ``flows.csv`` with the same values is a finished run."""


@dataclass(frozen=True)
class StudyPlan:
    """Every run of a study: the grid and what all its runs share."""

    site: MergeSite
    demands: list[dict[Side, float]]
    penetrations: list[float]
    seeds: list[int]
    policy: str
    """The automated cars' method (its name, for the CSVs)."""
    duration_s: float
    bin_s: float
    safety_mask: SafetyMask = DEFAULT_SAFETY_MASK
    warmup_s: float = 0.0
    """The run statistics leave out this start (whole bins: the road filling up from empty)."""

    def runs(self) -> Iterator[tuple[dict[str, str], FlowDemand]]:
        """(key, demand) of every run, demand by demand, then penetration, then seed."""
        for demand in self.demands:
            for p in self.penetrations:
                for seed in self.seeds:
                    flow = FlowDemand(demand, p, self.duration_s, seed, self.bin_s)
                    yield self.key(flow), flow

    def key(self, flow: FlowDemand) -> dict[str, str]:
        values: dict[str, Any] = {
            "net": self.site.path.name,
            "junction": self.site.junction_id,
            "demand": demand_label(dict(flow.veh_per_h)),
            "demand_main_veh_per_h": flow.veh_per_h.get("main", 0.0),
            "demand_merge_veh_per_h": flow.veh_per_h.get("merge", 0.0),
            "penetration": flow.penetration,
            "policy": self.policy,
            "safety_mask": self.safety_mask,
            "seed": flow.seed,
            "duration_s": flow.duration_s,
            "bin_s": flow.bin_s,
            "warmup_s": self.warmup_s,
        }
        return {k: _cell(v) for k, v in values.items()}


def _cell(value: Any) -> str:
    """A CSV cell: floats as ``repr`` (round-trips), whole floats without ``.0``, NaN empty."""
    if isinstance(value, bool):
        return str(int(value))
    if isinstance(value, float):
        if math.isnan(value):
            return ""
        return str(int(value)) if value.is_integer() and abs(value) < 1e15 else repr(value)
    return str(value)


def _read(path: Path, what: str) -> tuple[list[str], list[dict[str, str]]]:
    with path.open(newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        header = list(reader.fieldnames or [])
        rows = list(reader)
    if not set(KEY_COLUMNS) <= set(header):
        raise InputError(f"{path}: not a {what} written by idas-sumo cosim (its columns differ); use --force")
    return header, rows


def _write(path: Path, rows: list[dict[str, Any]]) -> None:
    header: list[str] = []
    for row in rows:
        header += [k for k in row if k not in header]
    with atomic_open(path, newline="") as f:
        writer = csv.DictWriter(f, fieldnames=header, lineterminator="\n")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: _cell(v) for k, v in row.items()})


def _key_of(row: dict[str, str]) -> tuple[str, ...]:
    return tuple(row.get(k, "") for k in KEY_COLUMNS)


def run_study(
    plan: StudyPlan,
    policy: Callable[[], Policy],
    out: Path,
    force: bool = False,
    on_run: Callable[[dict[str, str], Row | None], None] | None = None,
) -> tuple[Path, Path]:
    """Run every run of ``plan`` not yet in ``out/flows.csv``; ``policy`` makes the automated cars'
    policy (called once, only when a run has automated cars). ``on_run(key, row)`` after each run
    (``row`` None: skipped, finished before). Returns the two CSVs' paths."""
    resume = not force and (out / FLOWS_NAME).is_file()
    with output_directory(out, force, keep=resume, writes=(FLOWS_NAME, BINS_NAME, PLOT_NAME)) as where:
        flows_path, bins_path = where / FLOWS_NAME, where / BINS_NAME
        flows: list[dict[str, Any]] = []
        bins: list[dict[str, Any]] = []
        if resume:
            flows = list(_read(flows_path, "flows.csv")[1])
            if bins_path.is_file():
                bins = list(_read(bins_path, "bins.csv")[1])
        done = {_key_of(r) for r in flows}
        bins = [r for r in bins if _key_of(r) in done]  # a run's bins without its row: a run cut short
        made: list[Policy] = []
        for key, flow in plan.runs():
            if _key_of(key) in done:
                if on_run:
                    on_run(key, None)
                continue
            if flow.penetration > 0 and not made:
                made.append(policy())
            with tempfile.TemporaryDirectory(prefix="idas_sumo_cosim_") as tmp:
                result: RunResult = run_once(
                    plan.site, flow, made[0] if made else None, Path(tmp), plan.safety_mask, plan.warmup_s
                )
            flows.append({**key, **{k: v for k, v in result.row.items() if k not in key}})
            bins.extend({**key, **b} for b in result.bins)
            done.add(_key_of(key))
            _write(bins_path, bins)  # bins first: a row in flows.csv promises its bins are there
            _write(flows_path, flows)
            if on_run:
                on_run(key, result.row)
        if not flows_path.exists():
            _write(flows_path, flows)
            _write(bins_path, bins)
        if flows:
            plot_flows(flows_path, where / PLOT_NAME)
    return flows_path, bins_path


__all__ = ["BINS_NAME", "FLOWS_NAME", "KEY_COLUMNS", "PLOT_NAME", "StudyPlan", "run_study"]
