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
import re
import tempfile
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from idas_sumo import stops
from idas_sumo.cosim.demand import demand_label, profile_label
from idas_sumo.cosim.plots import plot_flows, plot_study
from idas_sumo.cosim.run import RunResult, run_once
from idas_sumo.cosim.stats import Row
from idas_sumo.env.actions import DEFAULT_SAFETY_MASK, SafetyMask
from idas_sumo.env.contracts import Policy
from idas_sumo.errors import IdasError, InputError, SimulationError
from idas_sumo.io_utils import atomic_open, output_directory
from idas_sumo.sim.flows import FlowDemand
from idas_sumo.sim.merge_detect import MergeSite, Side
from idas_sumo.sim.processes import ProcessPool, WorkerPool

FLOWS_NAME = "flows.csv"
BINS_NAME = "bins.csv"
PLOT_NAME = "flows.png"
TRAJECTORY_DIR = "trajectories"
"""With ``--trajectories``: one CSV per run here (``TRAJECTORY_COLUMNS``), for the time-space diagram."""
TRAJECTORY_COLUMNS = ("time_s", "vehicle", "road", "position_m", "speed_mps", "automated")
KEY_COLUMNS = (
    "net",
    "junction",
    "demand",
    "demand_profile",
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
OPTIONAL_KEYS = ("demand_profile",)
"""Key columns a ``flows.csv`` written before them lacks (read as empty: no profile)."""
OnRun = Callable[[dict[str, str], Row | None], None]


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
    profile: tuple[tuple[float, float], ...] = ()
    """The demand's time profile: (start s, multiplier) steps (empty: constant demand)."""
    trajectories: bool = False
    """Record every car's position on the merge's roads each second (``TRAJECTORY_DIR``)."""

    def runs(self) -> Iterator[tuple[dict[str, str], FlowDemand]]:
        """(key, demand) of every run, demand by demand, then penetration, then seed."""
        for demand in self.demands:
            for p in self.penetrations:
                for seed in self.seeds:
                    flow = FlowDemand(demand, p, self.duration_s, seed, self.bin_s, self.profile)
                    yield self.key(flow), flow

    def key(self, flow: FlowDemand) -> dict[str, str]:
        values: dict[str, Any] = {
            "net": self.site.path.name,
            "junction": self.site.junction_id,
            "demand": demand_label(dict(flow.veh_per_h)),
            "demand_profile": profile_label(flow.profile),
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
    if not set(KEY_COLUMNS) - set(OPTIONAL_KEYS) <= set(header):
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


@dataclass(frozen=True)
class RunRequest:
    """One run, as a worker is asked it (everything picklable: the policy is a factory it calls)."""

    site: MergeSite
    flow: FlowDemand
    policy: Callable[[], Policy]
    safety_mask: SafetyMask
    warmup_s: float
    trajectories: bool


def execute(request: RunRequest, made: list[Policy]) -> RunResult:
    """Run one request here; ``made`` holds the policy once made (made at the first run that needs it)."""
    if request.flow.penetration > 0 and not made:
        made.append(request.policy())
    with tempfile.TemporaryDirectory(prefix="idas_sumo_cosim_") as tmp:
        return run_once(
            request.site,
            request.flow,
            made[0] if made else None,
            Path(tmp),
            request.safety_mask,
            request.warmup_s,
            **({"trajectories": True} if request.trajectories else {}),
        )


class CosimServer:
    """A co-simulation worker (``sim.processes.Server``): runs one run per request, replies with its
    ``RunResult`` (or its error); it makes the policy once, at its first run with automated cars."""

    def __init__(self, init: None) -> None:
        self._made: list[Policy] = []

    def handle(self, request: RunRequest, shared: Any) -> tuple[str, object]:
        import traceback

        try:
            return ("ok", execute(request, self._made))
        except IdasError as err:
            return ("error", err)
        except Exception:
            return ("error", SimulationError(f"cosim worker failed:\n{traceback.format_exc()}"))

    def close(self) -> None:
        pass


def trajectory_name(key: dict[str, str]) -> str:
    """A run's trajectory file under ``TRAJECTORY_DIR``, named after what varies in a study."""
    demand = key["demand"].replace(" ", "_").replace("=", "")
    profile = f"_{key['demand_profile']}" if key.get("demand_profile") else ""
    name = f"{Path(key['net']).name.split('.')[0]}_{key['policy']}_{demand}{profile}_p{key['penetration']}"
    return re.sub(r"[^A-Za-z0-9_.+-]", "-", f"{name}_seed{key['seed']}") + ".csv"


def _write_trajectory(path: Path, rows: list[tuple[Any, ...]]) -> None:
    path.parent.mkdir(exist_ok=True)
    with atomic_open(path, newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(TRAJECTORY_COLUMNS)
        writer.writerows(rows)


class _Progress:
    """What a study has: earlier rows, and each new run's results by its index in the plan (written in
    plan order, whichever worker finished first, so the CSVs do not depend on the worker count)."""

    def __init__(self, flows: list[dict[str, Any]], bins: list[dict[str, Any]], where: Path) -> None:
        self.old_flows, self.old_bins, self.where = flows, bins, where
        self.new: dict[int, tuple[dict[str, Any], list[dict[str, Any]]]] = {}

    def add(self, index: int, key: dict[str, str], result: RunResult) -> None:
        row = {**key, **{k: v for k, v in result.row.items() if k not in key}}
        self.new[index] = (row, [{**key, **b} for b in result.bins])
        if result.trajectory is not None:
            _write_trajectory(self.where / TRAJECTORY_DIR / trajectory_name(key), result.trajectory)
        order = sorted(self.new)
        # bins first: a row in flows.csv promises its bins are there
        _write(self.where / BINS_NAME, self.old_bins + [b for i in order for b in self.new[i][1]])
        _write(self.where / FLOWS_NAME, self.old_flows + [self.new[i][0] for i in order])


Todo = list[tuple[int, dict[str, str], RunRequest]]


def _run_here(todo: Todo, progress: _Progress, on_run: OnRun | None) -> None:
    made: list[Policy] = []
    for index, key, request in todo:
        result = execute(request, made)
        progress.add(index, key, result)
        if on_run:
            on_run(key, result.row)


def _run_in_pool(
    todo: Todo, progress: _Progress, on_run: OnRun | None, workers: int, ray_address: str | None
) -> None:
    """The runs on ``workers`` workers, each given the next run as it finishes one."""
    factory = "idas_sumo.cosim.study:CosimServer"
    inits = [None] * min(workers, len(todo))
    pool: WorkerPool
    if ray_address is not None:
        from idas_sumo.distributed.ray_pool import RayPool  # only here: ray is an optional extra

        pool = RayPool(factory, inits, "cosim worker", ray_address)
    else:
        pool = ProcessPool(factory, inits, "cosim worker", capture_stderr=True)
    queue = deque(todo)
    busy: dict[int, tuple[int, dict[str, str], RunRequest]] = {}
    with pool:  # an error or a Ctrl-C here: leave no worker behind
        for w in range(len(inits)):
            busy[w] = queue.popleft()
            pool.submit({w: busy[w][2]})
        while busy:
            stops.check()
            for w in pool.finished(list(busy)):
                status, value = pool.result(w)
                if status == "error":
                    assert isinstance(value, Exception)
                    raise value
                assert isinstance(value, RunResult)
                index, key, _ = busy.pop(w)
                progress.add(index, key, value)
                if on_run:
                    on_run(key, value.row)
                if queue:
                    busy[w] = queue.popleft()
                    pool.submit({w: busy[w][2]})


def run_study(
    plan: StudyPlan,
    policy: Callable[[], Policy],
    out: Path,
    force: bool = False,
    on_run: OnRun | None = None,
    workers: int = 1,
    ray_address: str | None = None,
) -> tuple[Path, Path]:
    """Run every run of ``plan`` not yet in ``out/flows.csv``; ``policy`` makes the automated cars'
    policy (called once per process, only when a run has automated cars; picklable for workers).
    ``on_run(key, row)`` after each run (``row`` None: skipped, finished before). ``workers`` > 1 or
    ``ray_address``: the runs on a ``WorkerPool`` (processes, or Ray actors), the rows in plan order
    all the same. Returns the two CSVs' paths."""
    resume = not force and (out / FLOWS_NAME).is_file()
    writes = (FLOWS_NAME, BINS_NAME, PLOT_NAME, TRAJECTORY_DIR)
    with output_directory(out, force, keep=resume, writes=writes) as where:
        flows_path, bins_path = where / FLOWS_NAME, where / BINS_NAME
        flows: list[dict[str, Any]] = []
        bins: list[dict[str, Any]] = []
        if resume:
            flows = list(_read(flows_path, "flows.csv")[1])
            if bins_path.is_file():
                bins = list(_read(bins_path, "bins.csv")[1])
        done = {_key_of(r) for r in flows}
        bins = [r for r in bins if _key_of(r) in done]  # a run's bins without its row: a run cut short
        todo: Todo = []
        for index, (key, flow) in enumerate(plan.runs()):
            if _key_of(key) in done:
                if on_run:
                    on_run(key, None)
                continue
            done.add(_key_of(key))
            request = RunRequest(plan.site, flow, policy, plan.safety_mask, plan.warmup_s, plan.trajectories)
            todo.append((index, key, request))
        progress = _Progress(flows, bins, where)
        if todo and (workers > 1 or ray_address is not None):
            _run_in_pool(todo, progress, on_run, workers, ray_address)
        else:
            _run_here(todo, progress, on_run)
        if not flows_path.exists():
            _write(flows_path, flows)
            _write(bins_path, bins)
        if flows or progress.new:
            plot_flows(flows_path, where / PLOT_NAME)
    return flows_path, bins_path


def is_study(directory: Path) -> bool:
    """A folder ``idas-sumo cosim`` wrote (its ``flows.csv``), for ``idas-sumo plot``."""
    path = directory / FLOWS_NAME
    if not path.is_file():
        return False
    with path.open(newline="", encoding="utf-8") as f:
        header = next(csv.reader(f), [])
    return set(KEY_COLUMNS) - set(OPTIONAL_KEYS) <= set(header)


def plot_directory(directory: Path) -> list[Path]:
    """``idas-sumo plot DIR`` on a cosim folder: ``flows.png`` and each run's time-space diagram."""
    with output_directory(directory, False, keep=True, flag="plot"):
        return plot_study(directory, FLOWS_NAME, PLOT_NAME, TRAJECTORY_DIR)


__all__ = [
    "BINS_NAME",
    "FLOWS_NAME",
    "KEY_COLUMNS",
    "PLOT_NAME",
    "TRAJECTORY_COLUMNS",
    "TRAJECTORY_DIR",
    "CosimServer",
    "RunRequest",
    "StudyPlan",
    "execute",
    "is_study",
    "plot_directory",
    "run_study",
    "trajectory_name",
]
