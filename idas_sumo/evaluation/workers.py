"""``evaluate --workers N``: the evaluation's jobs split over N processes, each with its own engine.

Each worker gets a contiguous share of the (method, case) jobs in their fixed order, and the results are
put back in that order, so the CSVs do not depend on N (each job's numbers are those of its scenario
alone). The workers are a ``sim.processes.WorkerPool``, as ``train --workers`` has: processes started
and stopped by ``sim.processes.WorkerProcesses`` (fresh interpreters calling back on an authenticated
loopback socket: see there why), or with ``--ray-address`` Ray actors (distributed/ray_pool.py); the
task and its results travel through the pool.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from idas_sumo import stops
from idas_sumo.env.config import EnvConfig
from idas_sumo.errors import IdasError, SimulationError
from idas_sumo.evaluation.protocol import EpisodeResult, EvalJob, no_trajectory
from idas_sumo.sim.merge_detect import MergeSite
from idas_sumo.sim.processes import ProcessPool, WorkerPool


@dataclass(frozen=True)
class WorkerTask:
    """Everything a worker needs to run its share (policies are loaded in the worker)."""

    site: MergeSite
    """The evaluated merge, resolved by the caller (a worker does not parse the net)."""
    env: EnvConfig
    """The evaluation's episode rules."""
    jobs: tuple[EvalJob, ...]
    methods: tuple[str, ...]
    policy: Path | None
    others: str
    others_policy: Path | None
    seed: int
    copies: int
    tripinfo_dir: Path | None
    trajectories: bool


def split_jobs(n_jobs: int, workers: int) -> list[range]:
    """Contiguous shares of ``range(n_jobs)`` as equal as they come (never an empty one)."""
    workers = max(1, min(workers, n_jobs))
    bounds = [round(i * n_jobs / workers) for i in range(workers + 1)]
    return [range(bounds[i], bounds[i + 1]) for i in range(workers)]


def run_task(task: WorkerTask) -> Iterator[tuple[int, EpisodeResult]]:
    """Run a task's jobs here, in order: (index in the task, result)."""
    from idas_sumo.env.engine import MergeEngine
    from idas_sumo.evaluation.policies import LEARNED_METHODS, resolve_policy
    from idas_sumo.evaluation.protocol import run_jobs

    methods = {
        m: resolve_policy(m, task.policy if m in LEARNED_METHODS else None, task.seed) for m in task.methods
    }
    others = resolve_policy(task.others, task.others_policy, task.seed)
    engine = MergeEngine(task.site, copies=task.copies, seed=task.seed, config=task.env)
    try:
        for i, (_, result) in enumerate(run_jobs(engine, task.jobs, methods, others, task.tripinfo_dir)):
            yield i, result
    finally:
        engine.close()


class EvalServer:
    """An evaluation worker (``sim.processes.Server``): runs one task and replies with its results (or
    its error). Its engine lives only as long as the task (``run_task``)."""

    def __init__(self, init: None) -> None:
        pass

    def handle(self, task: WorkerTask, shared: Any) -> tuple[str, object]:
        import traceback

        try:
            # Without --trajectories only the rows travel back: a trajectory is dropped as its episode ends.
            rows = [
                (r.episode, r.flow, r.trajectory if task.trajectories else None) for _, r in run_task(task)
            ]
            return ("ok", rows)
        except IdasError as err:
            return ("error", err)
        except Exception:
            return ("error", SimulationError(f"evaluation worker failed:\n{traceback.format_exc()}"))

    def close(self) -> None:
        pass


def run_in_workers(
    tasks: Sequence[WorkerTask],
    on_done: Callable[[int], None] | None = None,
    ray_address: str | None = None,
) -> list[list[EpisodeResult]]:
    """Run each task in its own worker, all at once; their results, task by task. The workers are
    processes here, or Ray actors with ``ray_address``.

    ``on_done(i)``: task i's results are in (for a progress bar).
    """
    factory, inits = "idas_sumo.evaluation.workers:EvalServer", [None] * len(tasks)
    pool: WorkerPool
    if ray_address is not None:
        from idas_sumo.distributed.ray_pool import RayPool  # only here: ray is an optional extra

        pool = RayPool(factory, inits, "evaluation worker", ray_address)
    else:
        pool = ProcessPool(factory, inits, "evaluation worker", capture_stderr=True)
    outcomes: dict[int, tuple[str, object]] = {}
    with pool:  # an error or a Ctrl-C here: leave no worker behind
        pool.submit(dict(enumerate(tasks)))
        while len(outcomes) < len(tasks):
            stops.check()
            for i in pool.finished([i for i in range(len(tasks)) if i not in outcomes]):
                outcomes[i] = pool.result(i)
                if on_done is not None:
                    on_done(i)
    results: list[list[EpisodeResult]] = []
    for i in range(len(tasks)):
        status, value = outcomes[i]
        if status == "error":
            assert isinstance(value, Exception)
            raise value
        assert isinstance(value, list)
        results.append([EpisodeResult(e, f, no_trajectory() if t is None else t) for e, f, t in value])
    return results


__all__ = ["EvalServer", "WorkerTask", "run_in_workers", "run_task", "split_jobs"]
