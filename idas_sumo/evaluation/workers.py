"""``evaluate --workers N``: the evaluation's jobs split over N processes, each with its own engine.

Each worker gets a contiguous share of the (method, case) jobs in their fixed order, and the results are
put back in that order, so the CSVs do not depend on N (each job's numbers are those of its scenario
alone). Workers are started and stopped by ``sim.processes.WorkerProcesses``, as ``train --workers`` starts
its own (fresh interpreters calling back on an authenticated loopback socket: see there why); the task
and its results travel over that connection.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path

from idas_sumo.env.engine import SafetyMask
from idas_sumo.errors import IdasError, SimulationError
from idas_sumo.evaluation.protocol import EpisodeResult, EvalJob
from idas_sumo.sim.processes import WorkerProcesses, wait_any


@dataclass(frozen=True)
class WorkerTask:
    """Everything a worker needs to run its share (policies are loaded in the worker)."""

    net: Path
    jobs: tuple[EvalJob, ...]
    methods: tuple[str, ...]
    policy: Path | None
    others: str
    seed: int
    max_episode_s: float
    safety_mask: SafetyMask
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
    from idas_sumo.env.engine import EnvConfig, MergeEngine
    from idas_sumo.evaluation.policies import LEARNED_METHODS, resolve_policy
    from idas_sumo.evaluation.protocol import run_jobs

    methods = {
        m: resolve_policy(m, task.policy if m in LEARNED_METHODS else None, task.seed) for m in task.methods
    }
    others = resolve_policy(task.others, None, task.seed)
    engine = MergeEngine(
        task.net,
        copies=task.copies,
        seed=task.seed,
        config=EnvConfig(max_episode_s=task.max_episode_s, safety_mask=task.safety_mask),
    )
    try:
        for i, (_, result) in enumerate(run_jobs(engine, task.jobs, methods, others, task.tripinfo_dir)):
            yield i, result
    finally:
        engine.close()


def _serve(conn: Connection) -> None:
    """A worker (``WorkerProcesses`` entry): get the task, run it, send its results (or its error)."""
    import traceback

    task: WorkerTask = conn.recv()
    outcome: tuple[str, object]
    try:
        results = [r for _, r in run_task(task)]
        if not task.trajectories:
            for r in results:
                r.trajectory = r.trajectory.iloc[0:0]  # not written: do not ship it back
        outcome = ("ok", results)
    except IdasError as err:
        outcome = ("error", err)
    except Exception:
        outcome = ("error", SimulationError(f"evaluation worker failed:\n{traceback.format_exc()}"))
    conn.send(outcome)


def run_in_workers(
    tasks: Sequence[WorkerTask], on_done: Callable[[int], None] | None = None
) -> list[list[EpisodeResult]]:
    """Run each task in its own process, all at once; their results, task by task.

    ``on_done(i)``: task i's results are in (for a progress bar).
    """
    pool = WorkerProcesses(
        "idas_sumo.evaluation.workers:_serve", len(tasks), "evaluation worker", capture_stderr=True
    )
    try:
        for conn, task in zip(pool.conns, tasks, strict=True):
            conn.send(task)
        outcomes: dict[int, tuple[str, object]] = {}
        index = {id(conn): i for i, conn in enumerate(pool.conns)}
        while len(outcomes) < len(tasks):
            for conn in wait_any([c for i, c in enumerate(pool.conns) if i not in outcomes]):
                i = index[id(conn)]
                try:
                    outcomes[i] = conn.recv()
                except (EOFError, OSError):
                    code = pool.procs[i].wait()
                    tail = pool.stderr_tail(i)
                    raise SimulationError(
                        f"evaluation worker {i} exited with code {code} without results"
                        + (f": {tail}" if tail else "")
                    ) from None
                if on_done is not None:
                    on_done(i)
    except BaseException:  # an error or a Ctrl-C here: leave no worker behind
        pool.kill()
        raise
    pool.close()
    results: list[list[EpisodeResult]] = []
    for i in range(len(tasks)):
        status, value = outcomes[i]
        if status == "error":
            assert isinstance(value, Exception)
            raise value
        assert isinstance(value, list)
        results.append(value)
    return results


__all__ = ["WorkerTask", "run_in_workers", "run_task", "split_jobs"]
