"""``idas-sumo evaluate``: run a suite for one or more methods and write episodes, summary and flow CSV."""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Callable, Generator, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import IO

import pandas as pd

from idas_sumo.env.engine import EnvConfig, MergeEngine, Policy
from idas_sumo.env.scenario import start_room_m
from idas_sumo.errors import InputError
from idas_sumo.evaluation import DEFAULT_EVAL_COPIES
from idas_sumo.evaluation.metrics import (
    EPISODE_COLUMNS,
    FLOW_COLUMNS,
    SUMMARY_COLUMNS,
    TRAJECTORY_COLUMNS,
    summary_rows,
)
from idas_sumo.evaluation.policies import LEARNED_METHODS, METHOD_LABELS, POLICY_DIR, resolve_policy
from idas_sumo.evaluation.protocol import (
    DEFAULT_SUITE_SIZE,
    EpisodeResult,
    EvalCase,
    EvalConfig,
    EvalJob,
    Suite,
    eval_jobs,
    file_cases,
    load_eval_config,
    run_jobs,
    suite_cases,
    tripinfo_path,
)
from idas_sumo.evaluation.replay import write_replay_data
from idas_sumo.evaluation.sweep import (
    DRIVER_TYPE_COLUMNS,
    TREND_COLUMNS,
    driver_type_rows,
    trend_rows,
    verdict,
)
from idas_sumo.io_utils import atomic_open, output_directory, record_output, write_csv_atomic
from idas_sumo.sim.backend import require_display
from idas_sumo.sim.merge_detect import MergeSite, choose_merge

log = logging.getLogger(__name__)
SETTINGS_NAME = "settings.json"
"""Beside the CSVs: the settings that made them (methods, suite, seed, others, traffic, safety mask)."""
DRIVER_TYPES_NAME = "driver_types.csv"
"""The driver-types suite's merge times per method and b_type (evaluation/sweep.py)."""
TREND_NAME = "driver_types_trend.csv"
"""Its rank correlation of merge time against b_type, per method."""
TRAJECTORIES_NAME = "trajectories.csv"
"""With ``--trajectories``: every vehicle's row at every decision of every episode, written as episodes end."""


@dataclass(frozen=True)
class EvalRequest:
    net: Path
    methods: tuple[str, ...]
    suite: Suite = "paper"
    scenarios: int | None = None
    """Random scenarios of the paper suite, start offsets per b_type of the driver-types suite; None: the
    suite's default (``DEFAULT_SUITE_SIZE``)."""
    seed: int = 0
    others: str | None = None
    """Method for every non-ego vehicle; None: the shipped IDAS policy if present, else IDM."""
    policy: Path | None = None
    others_policy: Path | None = None
    """Checkpoint the others' learned method loads instead of the shipped file (``--others-policy``)."""
    out: Path = Path("results")
    force: bool = False
    """Write into an existing, non-empty ``out`` (its files are overwritten)."""
    fresh_out: bool = False
    """``out`` names a new directory: when it exists, write to the first free ``out-2``, ``out-3``, …"""
    trajectories: bool = False
    sumo_output: bool = False
    progress: bool = True
    gui: bool = False
    config: Path | None = None
    """TOML with [traffic], max_episode_s and safety_mask for the paper suite (see scenarios/eval_paper.toml)."""
    scenario_files: tuple[Path, ...] = ()
    """Evaluate these scenario TOML files instead of a suite (the ego is each file's first vehicle)."""
    workers: int = 1
    """Processes that share the episodes, each with its own SUMO (``evaluate --workers``); the CSVs do
    not depend on it."""
    copies: int = DEFAULT_EVAL_COPIES
    """Episodes run side by side in one SUMO run (1 with ``gui`` or ``sumo_output``: SUMO's own output
    and window are per episode). The CSVs do not depend on it."""
    env: EnvConfig | None = None
    """The episode rules every method runs by (max_episode_s, safety_mask, junction: which merge of
    ``net``); None: the ``config`` file's, else the defaults. The workers and the replay record get it."""
    site: MergeSite | None = None
    """``net``'s merge as the caller resolved it (``choose_merge(net, env.junction)``), so that the net is
    parsed once; None: resolved here."""
    ray_address: str | None = None
    """Run the ``workers`` on that Ray cluster (``evaluate --ray-address``, distributed/ray_pool.py)
    instead of this machine's processes; the CSVs do not depend on it."""


def default_others() -> str:
    return "idas" if (POLICY_DIR / LEARNED_METHODS["idas"]).exists() else "idm"


@dataclass(frozen=True)
class EvalOutput:
    out: Path
    """The directory the CSVs were written to."""
    summary: pd.DataFrame
    """The paper's table: one row per method (``summary.csv``)."""
    verdicts: tuple[str, ...] = ()
    """The driver-types suite: one line per method, the direction and rank correlation of merge time
    against the merge car's b_type."""
    written: tuple[str, ...] = ()
    """The names of the files written into ``out``."""


def run_evaluation(req: EvalRequest) -> EvalOutput:
    """Run the suite; write CSVs into ``req.out`` (atomically, only once everything ran).

    An interrupted or failed run removes the output directories it made that are still empty.
    """
    eval_config = load_eval_config(req.config) if req.config is not None else EvalConfig()
    env = req.env if req.env is not None else eval_config.env
    site = req.site if req.site is not None else choose_merge(req.net, env.junction)
    others_name = req.others or default_others()
    if req.scenarios is None and req.suite in DEFAULT_SUITE_SIZE:
        req = replace(req, scenarios=DEFAULT_SUITE_SIZE[req.suite])
    policies: dict[str, Policy] = {
        m: resolve_policy(m, req.policy if m in LEARNED_METHODS else None, req.seed) for m in req.methods
    }
    others_policy = resolve_policy(others_name, req.others_policy, req.seed)
    _check_gui(req)
    with output_directory(req.out, req.force, fresh=req.fresh_out, writes=("sumo", "replay")) as out:
        cases = _cases(req, site, eval_config)
        log.info("others run %s; %d cases x %d methods", others_name, len(cases), len(policies))
        jobs = eval_jobs(cases, list(policies))
        description = f"evaluate ({req.suite}, others: {others_name})"
        with (
            _sumo_output(out, req.sumo_output, jobs) as tripinfo_dir,
            _progress(req.progress, len(jobs), description) as advance,
            _trajectory_sink(out / TRAJECTORIES_NAME, req.trajectories) as sink,
        ):
            results: Iterable[tuple[EvalJob, EpisodeResult]]
            if req.ray_address is not None or (req.workers > 1 and len(jobs) > 1):
                results = _in_workers(req, site, env, jobs, others_name, tripinfo_dir, advance)
            else:
                results = _here(req, site, env, jobs, policies, others_policy, tripinfo_dir, advance)
            episodes, flows = _collect(results, sink)
        episode_frame = pd.DataFrame(episodes, columns=list(EPISODE_COLUMNS))
        summary = pd.DataFrame(summary_rows(episode_frame), columns=list(SUMMARY_COLUMNS))
        write_csv_atomic(episode_frame, out / "episodes.csv")
        write_csv_atomic(summary, out / "summary.csv")
        write_csv_atomic(pd.DataFrame(flows, columns=list(FLOW_COLUMNS)), out / "flow.csv")
        written = ["episodes.csv", "summary.csv", "flow.csv"]
        verdicts: list[str] = []
        if req.suite == "driver-types" and not req.scenario_files:
            verdicts = _write_driver_types(out, episode_frame, req.methods, others_name)
            written += [DRIVER_TYPES_NAME, TREND_NAME]
        with atomic_open(out / SETTINGS_NAME) as f:
            json.dump(_settings(req, others_name, eval_config, env), f, indent=2, default=str)
            f.write("\n")
        if req.trajectories:
            written.append(TRAJECTORIES_NAME)
        # What `idas-sumo replay` needs to run any of these episodes again (evaluation/replay.py).
        written.append(
            write_replay_data(
                out,
                req.net,
                cases,
                req.methods,
                req.policy,
                others_name,
                req.others_policy,
                req.seed,
                replace(env, junction=site.junction_id),
            )
        )
    return EvalOutput(out, summary, tuple(verdicts), tuple(written))


def _check_gui(req: EvalRequest) -> None:
    """``--gui`` shows one simulation, here, on a display."""
    require_display(req.gui)
    if req.gui and req.workers > 1:
        raise InputError("--gui shows one simulation: use it without --workers")
    if req.gui and req.ray_address is not None:
        raise InputError("--gui shows the episodes here: use it without --ray-address")


def _cases(req: EvalRequest, site: MergeSite, eval_config: EvalConfig) -> list[EvalCase]:
    """The scenario files' cases, else the suite's, on ``site``'s roads."""
    speed_limits = {"main": site.main.road.speed_limit_mps, "merge": site.merge.road.speed_limit_mps}
    if req.scenario_files:
        return file_cases(list(req.scenario_files), req.seed, speed_limits)
    lengths = {"main": site.main.length_m, "merge": site.merge.length_m}
    return suite_cases(
        req.suite,
        req.scenarios or 0,
        req.seed,
        speed_limits,
        eval_config.traffic,
        lengths,
        start_room_m(site),
    )


def _write_driver_types(
    out: Path, episode_frame: pd.DataFrame, methods: tuple[str, ...], others_name: str
) -> list[str]:
    """The driver-types suite's sweep and trend tables; one verdict line per method."""
    sweep = pd.DataFrame(driver_type_rows(episode_frame), columns=list(DRIVER_TYPE_COLUMNS))
    trends = trend_rows(episode_frame)
    write_csv_atomic(sweep, out / DRIVER_TYPES_NAME)
    write_csv_atomic(pd.DataFrame(trends, columns=list(TREND_COLUMNS)), out / TREND_NAME)
    labels = {m: METHOD_LABELS.get(m, m) for m in methods}
    return [
        verdict(row, labels[str(row["method"])], METHOD_LABELS.get(others_name, others_name))
        for row in trends
    ]


def _settings(req: EvalRequest, others: str, eval_config: EvalConfig, env: EnvConfig) -> dict[str, object]:
    """What made the CSVs (``settings.json``): the suite, the seed, the traffic, the episode rules."""
    return {
        "methods": list(req.methods),
        "suite": "scenario files" if req.scenario_files else req.suite,
        "scenarios": req.scenarios,
        "scenario_files": [str(p) for p in req.scenario_files],
        "seed": req.seed,
        "others": others,
        "policy": str(req.policy) if req.policy is not None else None,
        # Only when given: a record without it reads as before (the replay record names the file either way).
        **({"others_policy": str(req.others_policy)} if req.others_policy is not None else {}),
        "config": str(req.config) if req.config is not None else None,
        "traffic": asdict(eval_config.traffic),
        "max_episode_s": env.max_episode_s,
        "safety_mask": env.safety_mask,
    }


def _copies(req: EvalRequest) -> int:
    """SUMO's window and its own output files show one episode per run."""
    return 1 if req.gui or req.sumo_output else req.copies


def _here(
    req: EvalRequest,
    site: MergeSite,
    env: EnvConfig,
    jobs: list[EvalJob],
    policies: dict[str, Policy],
    others_policy: Policy,
    tripinfo_dir: Path | None,
    advance: Callable[[], None],
) -> Iterator[tuple[EvalJob, EpisodeResult]]:
    """Every job in this process, on one engine; each result as its episode ends (none is kept here)."""
    engine = MergeEngine(
        site,
        copies=_copies(req),
        seed=req.seed,
        config=env,
        gui=req.gui,
    )
    try:
        for job, result in run_jobs(engine, jobs, policies, others_policy, tripinfo_dir):
            advance()
            yield job, result
    finally:
        engine.close()


def _in_workers(
    req: EvalRequest,
    site: MergeSite,
    env: EnvConfig,
    jobs: list[EvalJob],
    others_name: str,
    tripinfo_dir: Path | None,
    advance: Callable[[], None],
) -> list[tuple[EvalJob, EpisodeResult]]:
    """The jobs split over ``req.workers`` processes, or Ray actors with ``req.ray_address``
    (evaluation/workers.py), back in job order."""
    from idas_sumo.evaluation.workers import WorkerTask, run_in_workers, split_jobs

    shares = split_jobs(len(jobs), req.workers)
    tasks = [
        WorkerTask(
            site=site,
            env=env,
            jobs=tuple(jobs[share.start : share.stop]),
            methods=req.methods,
            policy=req.policy,
            others=others_name,
            others_policy=req.others_policy,
            seed=req.seed,
            copies=_copies(req),
            tripinfo_dir=tripinfo_dir,
            trajectories=req.trajectories,
        )
        for share in shares
    ]

    def done(i: int) -> None:
        for _ in shares[i]:
            advance()

    per_task = run_in_workers(tasks, done, ray_address=req.ray_address)
    return [
        (job, result)
        for task, results in zip(tasks, per_task, strict=True)
        for job, result in zip(task.jobs, results, strict=True)
    ]


def _collect(
    results: Iterable[tuple[EvalJob, EpisodeResult]], sink: _TrajectorySink | None
) -> tuple[list[dict[str, object]], list[dict[str, object]]]:
    """Each result's episode and flow rows, in job order; its trajectory goes to ``sink`` (if any) and
    is dropped, so that memory does not grow with the episodes' steps."""
    episodes, flows = [], []
    each = iter(results)
    try:
        for job, result in each:
            episodes.append(result.episode)
            flows.append(result.flow)
            if sink is not None:
                sink.write(result.trajectory.assign(scenario=job.case.scenario.name, run_method=job.method))
    finally:
        if isinstance(each, Generator):  # a failure here: close the engine now, not when collected
            each.close()
    return episodes, flows


class _TrajectorySink:
    """``trajectories.csv`` written one episode at a time: the same bytes as one frame of them all."""

    COLUMNS = ("scenario", "run_method", *TRAJECTORY_COLUMNS)

    def __init__(self, f: IO[str]) -> None:
        self.f = f
        self.header = True

    def write(self, trajectory: pd.DataFrame) -> None:
        trajectory[list(self.COLUMNS)].to_csv(
            self.f, index=False, header=self.header, lineterminator="\n", na_rep=""
        )
        self.header = False


@contextlib.contextmanager
def _sumo_output(out: Path, enabled: bool, jobs: Sequence[EvalJob]) -> Iterator[Path | None]:
    """``--sumo-output``: the folder SUMO writes each job's tripinfo into (itself, in place, so each
    file is recorded as the tool's up front); None without it. A run that fails removes the tripinfo
    files SUMO wrote during it (a half-written one made the rerun refused: the folder held files) and
    the folder if it made it; files of an earlier run that it did not touch stay."""
    if not enabled:
        yield None
        return
    folder = out / "sumo"
    made = not folder.exists()
    folder.mkdir(exist_ok=True)
    paths = [tripinfo_path(folder, job) for job in jobs]
    for path in paths:
        record_output(path)
    before = {path: _stamp(path) for path in paths}
    try:
        yield folder
    except BaseException:
        for path in paths:
            if _stamp(path) not in (None, before[path]):  # written during this run
                with contextlib.suppress(OSError):
                    path.unlink()
        if made:
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise


def _stamp(path: Path) -> tuple[int, int] | None:
    """A file's modification time and size (None: none there)."""
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_mtime_ns, st.st_size


@contextlib.contextmanager
def _trajectory_sink(path: Path, enabled: bool) -> Iterator[_TrajectorySink | None]:
    """A sink into a temp file beside ``path``, renamed into place when the block completes; None
    when trajectories were not asked for."""
    if not enabled:
        yield None
        return
    with atomic_open(path) as f:
        yield _TrajectorySink(f)


class _progress:
    """A rich progress bar (or nothing) that yields an ``advance()`` callable."""

    def __init__(self, enabled: bool, total: int, description: str) -> None:
        self.enabled = enabled
        self.total = total
        self.description = description

    def __enter__(self) -> Callable[[], None]:
        if not self.enabled:
            return lambda: None
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self._bar = Progress(
            "[progress.description]{task.description}",
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
            transient=False,
        )
        self._bar.__enter__()
        task = self._bar.add_task(self.description, total=self.total)
        return lambda: self._bar.advance(task)

    def __exit__(self, *exc: object) -> None:
        if self.enabled:
            self._bar.__exit__(None, None, None)
