"""``evaluate --workers N``: the evaluation's jobs split over N processes, each with its own engine.

Each worker gets a contiguous share of the (method, case) jobs in their fixed order, and the results are
put back in that order, so the CSVs do not depend on N (each job's numbers are those of its scenario
alone). Workers are fresh interpreters started with subprocess, as sim/backend.py starts its SUMO
child, not multiprocessing's spawn: that would re-import the user's ``__main__``, so a script calling
``run_evaluation`` without an ``if __name__ == "__main__":`` guard would run itself again. The task
and the results travel as pickle files in a private temporary directory (libsumo prints on stdout).
"""

from __future__ import annotations

import pickle
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from idas_sumo.env.engine import SafetyMask
from idas_sumo.errors import IdasError, SimulationError
from idas_sumo.evaluation.protocol import EpisodeResult, EvalJob

_CHILD_CODE = (
    "import sys; sys.path.append(sys.argv[1]); "
    "from idas_sumo.evaluation.workers import _child_main; _child_main(sys.argv[2], sys.argv[3])"
)
_POLL_S = 0.2


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


def _child_main(task_path: str, result_path: str) -> None:
    """A worker: run the task, write its results (or its error) as a pickle, exit."""
    import signal
    import traceback

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent owns Ctrl-C and stops us
    task: WorkerTask = pickle.loads(Path(task_path).read_bytes())
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
    Path(result_path).write_bytes(pickle.dumps(outcome))


def run_in_workers(
    tasks: Sequence[WorkerTask], on_done: Callable[[int], None] | None = None
) -> list[list[EpisodeResult]]:
    """Run each task in its own process, all at once; their results, task by task.

    ``on_done(i)``: task i's process has ended (for a progress bar).
    """
    import subprocess
    import sys
    import tempfile
    import time

    package_root = str(Path(__file__).resolve().parents[2])
    procs: list[subprocess.Popen[bytes]] = []
    with tempfile.TemporaryDirectory(prefix="idas_sumo_eval_") as tmp:
        workdir = Path(tmp)
        try:
            for i, task in enumerate(tasks):
                task_path = workdir / f"task{i}.pickle"
                task_path.write_bytes(pickle.dumps(task))
                procs.append(
                    subprocess.Popen(
                        [
                            sys.executable,
                            "-P",
                            "-c",
                            _CHILD_CODE,
                            package_root,
                            str(task_path),
                            str(workdir / f"result{i}.pickle"),
                        ],
                        stdin=subprocess.DEVNULL,
                        stdout=subprocess.DEVNULL,
                        stderr=(workdir / f"stderr{i}.txt").open("wb"),
                        start_new_session=True,
                    )
                )
            pending = set(range(len(procs)))
            while pending:
                for i in sorted(pending):
                    if procs[i].poll() is not None:
                        pending.discard(i)
                        if on_done is not None:
                            on_done(i)
                time.sleep(_POLL_S)
        finally:  # an error or a Ctrl-C here: leave no worker behind
            for p in procs:
                if p.poll() is None:
                    p.kill()
                    p.wait()
        results: list[list[EpisodeResult]] = []
        for i, p in enumerate(procs):
            path = workdir / f"result{i}.pickle"
            if not path.exists():
                tail = (workdir / f"stderr{i}.txt").read_text(errors="replace").strip().splitlines()[-5:]
                raise SimulationError(
                    f"evaluation worker {i} exited with code {p.returncode} without results"
                    + (": " + " | ".join(tail) if tail else "")
                )
            status, value = pickle.loads(path.read_bytes())
            if status == "error":
                assert isinstance(value, Exception)
                raise value
            assert isinstance(value, list)
            results.append(value)
    return results


__all__ = ["WorkerTask", "run_in_workers", "run_task", "split_jobs"]
