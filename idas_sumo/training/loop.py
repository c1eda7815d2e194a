"""The training loop, top to bottom: for each stage, rounds of collect, update, log, validate, checkpoint.

``run_training`` is what ``idas-sumo train`` calls; it reads as the run goes, and each part it
calls follows it in this file in that order. One round = ``episodes_per_update`` episodes collected
with the current actor (by 1 in-process worker or W processes), then one learner update on all
their agent-steps, then one metrics row per episode. With ``[geometry]`` (training/geometry.py) a round first draws its generated net, and ``geometries.csv`` gets one
row per round saying which. Randomness: one numpy generator draws the scenarios, one torch generator draws each
episode's action-sampling seed; both are saved in every checkpoint, so ``resume`` continues exactly where the last
checkpoint left off.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import sys
import threading
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, get_args

import numpy as np
import torch
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from idas_sumo import stops
from idas_sumo.agents.learner import Learner
from idas_sumo.agents.rollout import EpisodeStats
from idas_sumo.env.net_needs import RoadNeeds, check_road_lengths, road_needs
from idas_sumo.env.scenario import Road, generate_scenario, start_room_m
from idas_sumo.errors import InputError
from idas_sumo.io_utils import holds_files, output_directory
from idas_sumo.resources import resolve_user_path
from idas_sumo.sim.backend import require_display
from idas_sumo.sim.merge_detect import MergeSite, choose_merge
from idas_sumo.sim.multinet import build_copies
from idas_sumo.sim.net_cache import cached_net
from idas_sumo.sim.netgen import NetParams
from idas_sumo.training.checkpoint import TrainingCheckpoint, load_checkpoint, save_checkpoint
from idas_sumo.training.config import RESUME_FIELDS, Stage, TrainConfig, ValidationCriterion
from idas_sumo.training.curriculum import StagePlan, plan_stages
from idas_sumo.training.geometry import GEOMETRY_COLUMNS, GeometryConfig, draw_geometry, geometry_corners
from idas_sumo.training.heap import frozen_heap, keep_freed_blocks
from idas_sumo.training.metrics import METRICS_NAME, TENSORBOARD_DIR, MetricsSink
from idas_sumo.training.validation import (
    VALIDATION_COLUMNS,
    VALIDATION_NAME,
    ValidationScore,
    score_episodes,
    split_evenly,
    validation_key,
    validation_tasks,
)
from idas_sumo.training.workers import EpisodeTask, RolloutWorkers, make_workers

__all__ = ["CHECKPOINT_NAME", "run_training", "stored_config"]

log = logging.getLogger(__name__)

CHECKPOINT_NAME = "checkpoint.pt"
"""The latest checkpoint of a run directory (what ``--resume`` reads)."""
GEOMETRIES_NAME = "geometries.csv"
"""With ``[geometry]``: the net each round ran on (``GEOMETRY_COLUMNS``)."""
GEOMETRY_SOURCE = "[geometry]"
"""What the road checks name as the source of a drawn net's episode rules."""
SUCCESS_WINDOW = 100  # episodes in the progress bar's running success rate


def run_training(
    net: MergeSite | Path | str,
    config: TrainConfig,
    out_dir: Path | str,
    resume: bool = False,
    progress: bool = True,
    gui: bool = False,
    force: bool = False,
    ray_address: str | None = None,
) -> Path:
    """Train as ``config`` says on ``net`` (the merge site, resolved once by the caller, travels to every
    worker; or a net file and ``config.env.junction``); write checkpoints and ``metrics.csv`` under ``out_dir``.

    Returns the final checkpoint (``out_dir/<last stage>.pt``). ``resume`` continues the run in
    ``out_dir`` from its ``checkpoint.pt`` with the saved config, taking only ``RESUME_FIELDS``
    (workers, copies, the stage budgets) from ``config``: a larger budget extends a finished run. Without
    ``resume``, an ``out_dir`` that holds files is refused unless ``force``, which first removes the
    files earlier runs recorded there (io_utils.output_directory); two runs never share it. ``gui`` shows the rollouts in sumo-gui (one worker only). ``ray_address``: the
    rollout workers are ``config.rollout_workers()`` Ray actors on that cluster (distributed/ray_pool.py; the
    learner stays here); the run is the same as with local workers. Ctrl-C saves a checkpoint of the
    completed rounds, then re-raises KeyboardInterrupt.
    """
    out_dir = Path(out_dir)
    net_path = net.path if isinstance(net, MergeSite) else Path(net)
    keep_freed_blocks()
    _check_request(net_path, config, out_dir, resume=resume, gui=gui, force=force, ray_address=ray_address)
    resumed = _read_resume_point(out_dir) if resume else None
    if resumed is not None:
        config = _resumed_config(resumed.config, config)
    elif not force:
        _refuse_used_out_dir(out_dir)
    init_weights = _init_weights(config) if resumed is None else None
    names = [path.name for path in _run_outputs(out_dir)]
    with output_directory(out_dir, force, keep=resume, writes=names, clear_first=True):
        return _train_in(net, config, out_dir, resumed, init_weights, gui, ray_address, progress)


def _train_in(
    net: MergeSite | Path | str,
    config: TrainConfig,
    out_dir: Path,
    resumed: TrainingCheckpoint | None,
    init_weights: dict[str, Any] | None,
    gui: bool,
    ray_address: str | None,
    progress: bool,
) -> Path:
    """``run_training`` once ``out_dir`` is locked for the run (and, with ``force``, cleared)."""
    plans = plan_stages(config)
    site = net if isinstance(net, MergeSite) else choose_merge(Path(net), config.env.junction)
    geometry_needs = _check_geometry(config) if config.geometry is not None else None
    state = _starting_state(config, plans, out_dir, resumed)

    run = _Run(config, out_dir, _site_limits(site), start_room=start_room_m(site))
    # On resume, the metrics rows past the checkpoint go (they are written again).
    keep_below = state.global_episode if resumed is not None else None
    with (
        make_workers(
            site,
            config.env,
            config.seed,
            config.rollout_workers(gui),
            config.copies,
            gui=gui,
            ray_address=ray_address,
        ) as workers,
        MetricsSink(out_dir, keep_below) as metrics_sink,
        (
            _validation_sink(out_dir, keep_below) if config.validate_every else contextlib.nullcontext()
        ) as validation_sink,
        (
            _geometry_sink(out_dir, keep_below) if config.geometry is not None else contextlib.nullcontext()
        ) as geometry_sink,
        _make_progress(progress and sys.stderr.isatty()) as bar,
    ):
        if config.geometry is not None and geometry_sink is not None and geometry_needs is not None:
            run = dataclasses.replace(
                run,
                geometry=_GeometryDraws(
                    config.geometry, geometry_needs, geometry_sink, 1 if gui else config.copies
                ),
            )
        final = _train_stages(
            run, plans, state, resumed, init_weights, workers, metrics_sink, validation_sink, bar
        )
        if run.geometry is not None:
            run.geometry.wait()
    return final


def _starting_state(
    config: TrainConfig,
    plans: list[StagePlan],
    out_dir: Path,
    resumed: TrainingCheckpoint | None,
) -> _RunState:
    """Where the run starts: where ``resumed`` left off (its later best weights dropped), or at episode 0."""
    if resumed is not None:
        state = _RunState.resume(resumed, plans, out_dir / CHECKPOINT_NAME)
        _drop_best_after(out_dir, state.global_episode)
        return state
    return _RunState.start(config.seed)


def _train_stages(
    run: _Run,
    plans: list[StagePlan],
    state: _RunState,
    resumed: TrainingCheckpoint | None,
    init_weights: dict[str, Any] | None,
    workers: RolloutWorkers,
    metrics: MetricsSink,
    validation_sink: MetricsSink | None,
    bar: Progress,
) -> Path:
    """Each stage from where ``state`` stands, each with its learner and validation. Returns the last
    ``<stage>.pt``."""
    final = run.latest
    learner: Learner | None = None
    for stage_index in range(state.stage_index, len(plans)):
        plan = plans[stage_index]
        # The checkpoint's own stage continues from it; a later stage starts afresh.
        resumed_here = resumed if resumed is not None and stage_index == resumed.stage_index else None
        learner = _stage_learner(
            plan,
            seed=run.config.seed + stage_index,
            resumed=resumed_here,
            previous=learner,
            init_weights=init_weights if stage_index == 0 else None,
        )
        state.enter_stage(stage_index)
        validation = (
            None
            if validation_sink is None
            else _StageValidation.start(run, plan, workers, validation_sink, resumed_here)
        )
        with frozen_heap():  # (the stage's learner, the workers, the imports: none of it is garbage)
            _train_stage(run, plan, learner, state, workers, metrics, validation, bar)
        final = _finish_stage(run, plan, learner, state, validation)
    return final


# --- preparing the run directory --------------------------------------------------------------------


def _check_request(
    net_path: Path,
    config: TrainConfig,
    out_dir: Path,
    *,
    resume: bool,
    gui: bool,
    force: bool,
    ray_address: str | None,
) -> None:
    """Refuse a request that cannot run, before anything is read or written."""
    if not net_path.is_file():
        raise InputError(f"{net_path}: network file not found")
    if gui and config.workers > 1:
        raise InputError("--gui needs --workers 1")
    if gui and ray_address is not None:
        raise InputError("--gui shows the rollouts here: use it without --ray-address")
    require_display(gui)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir}: exists and is not a directory")
    if resume and force:
        raise InputError("--resume and --force exclude each other")


def _check_geometry(config: TrainConfig) -> RoadNeeds:
    """Refuse ``[geometry]`` ranges whose nets the run's scenarios cannot use (``env/net_needs.py``,
    on the two hardest draws, built now through the net cache) before anything is written; returns
    the bounds every drawn net is checked against."""
    assert config.geometry is not None
    start_range = max(config.robot_traffic.start_range_m, config.intelligent_traffic.start_range_m)
    needs = road_needs(start_range, config.longest_episode_s, GEOMETRY_SOURCE)
    for params in geometry_corners(config.geometry):
        try:
            check_road_lengths(choose_merge(cached_net(params)), needs)
        except InputError as err:
            raise InputError(
                f"{GEOMETRY_SOURCE}: ranges draw a net the scenarios cannot use: {err}"
            ) from None
    return needs


def _read_resume_point(out_dir: Path) -> TrainingCheckpoint:
    latest = out_dir / CHECKPOINT_NAME
    if not latest.exists():
        raise InputError(f"{latest}: no checkpoint to resume from")
    return load_checkpoint(latest)


def stored_config(out_dir: Path) -> TrainConfig:
    """The config of the run in ``out_dir`` (from its ``checkpoint.pt``), as ``--resume`` continues it."""
    return load_checkpoint(out_dir / CHECKPOINT_NAME).config


def _resumed_config(saved: TrainConfig, requested: TrainConfig) -> TrainConfig:
    """The run's own config with ``RESUME_FIELDS`` from ``requested``; other new values are ignored."""
    ignored = [
        f.name
        for f in dataclasses.fields(TrainConfig)
        if f.name not in RESUME_FIELDS and getattr(saved, f.name) != getattr(requested, f.name)
    ]
    if ignored:
        log.warning("resuming with the checkpoint's config; ignoring new values for %s", ", ".join(ignored))
    return dataclasses.replace(saved, **{name: getattr(requested, name) for name in RESUME_FIELDS})


def _refuse_used_out_dir(out_dir: Path) -> None:
    """A new run (no ``force``) writes only into an empty or new ``out_dir``."""
    if not holds_files(out_dir):
        return
    if (out_dir / CHECKPOINT_NAME).exists():
        raise InputError(
            f"{out_dir}: already holds a training run; pass --resume to continue it, --force to "
            "start over, or choose another --out"
        )
    raise InputError(
        f"--out {out_dir}: directory exists and is not empty (use --force to overwrite its files)"
    )


def _init_weights(config: TrainConfig) -> dict[str, Any] | None:
    """The learner state ``init_from`` names, which starts the first stage (None without one)."""
    if not config.init_from:
        return None
    try:
        # A shipped policy is found from any directory by its package path (policies/warm_start.pt).
        return load_checkpoint(resolve_user_path(config.init_from)).learner
    except InputError as err:
        raise InputError(
            f"init_from: {err} (a path from the working directory, or a shipped policy as "
            "policies/NAME.pt; scripts/pretrain_imitation.py makes a warm start of your own)"
        ) from None


def _run_outputs(out_dir: Path) -> list[Path]:
    """Every file or folder a training run writes into ``out_dir``."""
    stages = {plan.name for stage in get_args(Stage) for plan in plan_stages(TrainConfig(stage=stage))}
    names = [CHECKPOINT_NAME, METRICS_NAME, VALIDATION_NAME, GEOMETRIES_NAME, TENSORBOARD_DIR]
    names += [f"{stage}{suffix}" for stage in sorted(stages) for suffix in (".pt", "_best.pt")]
    return [out_dir / name for name in names]


def _drop_best_after(out_dir: Path, global_episode: int) -> None:
    """Delete every ``<stage>_best.pt`` saved after ``global_episode``: its weights come from training
    that resuming from that checkpoint discards."""
    for path in _run_outputs(out_dir):
        stale = (
            path.name.endswith("_best.pt")
            and path.is_file()
            and load_checkpoint(path).global_episode > global_episode
        )
        if stale:
            log.info("removing %s: saved after the checkpoint the run resumes from", path)
            path.unlink()


def _validation_sink(out_dir: Path, keep_below: int | None) -> MetricsSink:
    """``validation.csv``. A validation row is stamped with the episode count it was scored at, so on
    resume the one at the checkpoint's own count stays."""
    return MetricsSink(
        out_dir,
        None if keep_below is None else keep_below + 1,
        name=VALIDATION_NAME,
        columns=VALIDATION_COLUMNS,
        tensorboard_keys=(),
    )


def _geometry_sink(out_dir: Path, keep_below: int | None) -> MetricsSink:
    """``geometries.csv``: a round's row carries its first episode, so on resume the rounds the
    checkpoint counted stay."""
    return MetricsSink(
        out_dir, keep_below, name=GEOMETRIES_NAME, columns=GEOMETRY_COLUMNS, tensorboard_keys=()
    )


# --- the run's state --------------------------------------------------------------------------------


@dataclasses.dataclass
class _GeometryDraws:
    """``[geometry]``: the ranges, the bounds each drawn net must meet, ``geometries.csv``, and the
    merge site of every net drawn so far (read once per net)."""

    ranges: GeometryConfig
    needs: RoadNeeds
    sink: MetricsSink
    copies: int
    """Episodes side by side in a rollout worker: the multi-copy net each worker runs (``prefetch``)."""
    sites: dict[Path, MergeSite] = dataclasses.field(default_factory=dict)
    _ahead: threading.Thread | None = None

    def draw(self, rng: np.random.Generator) -> tuple[NetParams, MergeSite]:
        """The round's geometry from the run's generator, and its net's merge site."""
        self.wait()  # never two builds of one net from this process
        params = draw_geometry(rng, self.ranges)
        path = cached_net(params)
        site = self.sites.get(path)
        if site is None:
            site = choose_merge(path)
            check_road_lengths(site, self.needs)
            self.sites[path] = site
        return params, site

    def prefetch(self, rng: np.random.Generator) -> None:
        """Build, while the round runs, the nets the next round will most likely draw: its geometry
        is the next draw of ``rng``, read from a copy (``rng`` itself does not move). Built ahead, the
        workers read the net and its multi-copy net from the caches. Only the caches see it: a wrong guess (a stage's last round) or a failed
        build changes nothing, the round builds what it draws itself."""
        peek = np.random.Generator(type(rng.bit_generator)())
        peek.bit_generator.state = rng.bit_generator.state
        params = draw_geometry(peek, self.ranges)
        self._ahead = threading.Thread(target=self._build, args=(params,), daemon=True)
        self._ahead.start()

    def wait(self) -> None:
        """Let a build ahead finish (the run is over: no half-built net left behind)."""
        if self._ahead is not None:
            self._ahead.join()
            self._ahead = None

    def _build(self, params: NetParams) -> None:
        with contextlib.suppress(Exception):
            path = cached_net(params)
            if self.copies > 1:
                build_copies(path, self.copies)


@dataclasses.dataclass(frozen=True)
class _Run:
    """What stays fixed while a run trains."""

    config: TrainConfig
    out_dir: Path
    speed_limits: dict[Road, float]
    """The run's net's (every round without ``[geometry]``, and validation)."""
    started: float = dataclasses.field(default_factory=time.perf_counter)
    geometry: _GeometryDraws | None = None
    """``[geometry]``: each round draws its own net."""
    start_room: dict[Road, float] | None = None
    """The run's net's room for starts on each road (``start_room_m``)."""

    @property
    def latest(self) -> Path:
        return self.out_dir / CHECKPOINT_NAME

    def wall_s(self) -> float:
        """Seconds since the run (this process's part of it) started."""
        return time.perf_counter() - self.started


_RngStates = tuple[Mapping[str, Any], torch.Tensor]


@dataclasses.dataclass
class _RunState:
    """Where the run stands and the generators that continue it: what a checkpoint saves.

    A round draws its episodes first and counts them when they are done, so between the two the
    generators are ahead of the counts; a checkpoint holds the generators as they were when the
    counts were last advanced (``counted_rng``), whenever it is taken, Ctrl-C included.
    """

    np_rng: np.random.Generator
    """Draws the scenarios."""
    torch_rng: torch.Generator
    """Draws each episode's action-sampling seed."""
    stage_index: int = 0
    episode: int = 0
    """Episodes completed in the current stage."""
    global_episode: int = 0
    """Episodes completed in every stage of the run."""
    counted_rng: _RngStates = dataclasses.field(init=False)
    """The generators' states when the counts were last advanced (or set)."""
    ahead: list[EpisodeTask] = dataclasses.field(default_factory=list)
    """The next round's episodes, drawn during this round (the workers load them while they wait)."""

    def __post_init__(self) -> None:
        self.counted_rng = self.rng_states()

    @classmethod
    def start(cls, seed: int) -> _RunState:
        return cls(np.random.default_rng(seed), torch.Generator().manual_seed(seed))

    @classmethod
    def resume(cls, checkpoint: TrainingCheckpoint, plans: list[StagePlan], path: Path) -> _RunState:
        """Where ``checkpoint`` (read from ``path``) left off, if it fits this run's plan and budgets."""
        c = checkpoint
        if c.stage_index >= len(plans) or plans[c.stage_index].name != c.stage:
            raise InputError(f"{path}: stage {c.stage!r} does not belong to this run's plan")
        budget = plans[c.stage_index].episodes
        if c.episode > budget:
            raise InputError(
                f"{path}: the run is at episode {c.episode} of stage {c.stage!r}; a budget of {budget} "
                f"episodes ends before that (give --episodes {c.episode} or more)"
            )
        np_rng, torch_rng = np.random.default_rng(c.config.seed), torch.Generator()
        np_rng.bit_generator.state = c.numpy_rng
        torch_rng.set_state(c.torch_rng)
        return cls(np_rng, torch_rng, c.stage_index, c.episode, c.global_episode)

    def enter_stage(self, stage_index: int) -> None:
        """Count the episodes of ``stage_index`` from 0, unless the run is in that stage already."""
        if stage_index != self.stage_index:
            self.stage_index, self.episode = stage_index, 0

    def advance(self, episodes: int, drawn: _RngStates) -> None:
        """Count ``episodes`` as done; ``drawn``: the generators' states just after their draws (the next
        round's may have come since)."""
        self.episode += episodes
        self.global_episode += episodes
        self.counted_rng = drawn

    def rng_states(self) -> _RngStates:
        return self.np_rng.bit_generator.state, self.torch_rng.get_state()

    def checkpoint(self, learner: Learner, config: TrainConfig, plan: StagePlan) -> TrainingCheckpoint:
        """The run's completed work: ``learner``, the counts, and the generators as counted."""
        numpy_state, torch_state = self.counted_rng
        return TrainingCheckpoint(
            learner=learner.state_dict(),
            config=config,
            stage=plan.name,
            stage_index=self.stage_index,
            episode=self.episode,
            global_episode=self.global_episode,
            numpy_rng=dict(numpy_state),
            torch_rng=torch_state.clone(),
        )


# --- one stage --------------------------------------------------------------------------------------


def _stage_learner(
    plan: StagePlan,
    seed: int,
    resumed: TrainingCheckpoint | None,
    previous: Learner | None,
    init_weights: dict[str, Any] | None,
) -> Learner:
    """The stage's learner: the checkpoint's when the run resumes in this stage, else the previous
    stage's networks (the curriculum's stage 2), else ``init_weights``, else fresh ones; with ``anchor_coef``
    its anchor is what it starts from."""
    learner = Learner(plan.learner, seed=seed)
    if resumed is not None:
        learner.load_state_dict(resumed.learner)
    elif plan.init_from_previous and previous is not None:
        learner.load_state_dict(previous.state_dict(), load_optimisers=False)
    elif init_weights is not None:
        learner.load_state_dict(init_weights, load_optimisers=False)
    if resumed is None and plan.learner.anchor_coef > 0.0:
        learner.anchor_to_start()  # π₀: the weights this stage starts from (a resumed stage keeps its own)
    return learner


@dataclasses.dataclass
class _StageValidation:
    """One stage's held-out scenarios, its ``validation.csv`` sink and the best score so far."""

    workers: RolloutWorkers
    groups: list[tuple[MergeSite | None, list[EpisodeTask]]]
    """The held-out scenarios, by the net they run on (None: the run's own)."""
    sink: MetricsSink
    best_path: Path
    criterion: ValidationCriterion = "joint_return"
    best: tuple[float, float] = (float("-inf"), float("-inf"))
    validated_at: int = -1
    """The stage episode of the last validation."""
    owed: bool = False
    """A resumed run owes the validation of the checkpoint's last round (Ctrl-C or a kill came during it)."""

    @classmethod
    def start(
        cls,
        run: _Run,
        plan: StagePlan,
        workers: RolloutWorkers,
        sink: MetricsSink,
        resumed: TrainingCheckpoint | None,
    ) -> _StageValidation:
        """The stage's validation; ``resumed``: the checkpoint a run resumes from in this stage."""
        config = run.config
        validation = cls(
            workers,
            _validation_groups(run, plan),
            sink,
            run.out_dir / f"{plan.name}_best.pt",
            config.validation_criterion,
        )
        if resumed is not None:
            # The stage's validations before the checkpoint: the best so far, and whether the
            # checkpoint's own episode was validated already (then not twice).
            kept = [r for r in sink.kept if r["stage"] == plan.name]
            validation.best = resumed_best(kept, validation.best_path, validation.criterion)
            if kept and int(kept[-1]["episode"]) == resumed.episode:
                validation.validated_at = resumed.episode
            validated_to = (
                int(kept[-1]["global_episode"]) if kept else resumed.global_episode - resumed.episode
            )
            validation.owed = _passed_multiple(validated_to, resumed.global_episode, config.validate_every)
        return validation

    @property
    def best_return(self) -> float:
        """The joint return of the best validation so far (what the progress bar shows)."""
        return self.best[0] if self.criterion == "joint_return" else self.best[1]

    def run(self, learner: Learner, checkpoint: TrainingCheckpoint, wall_s: float) -> None:
        """Score the greedy policy; save ``checkpoint`` as ``best_path`` when it beats the best so far."""
        score = score_episodes(
            [e.stats for net, tasks in self.groups for e in self.workers.run(learner, tasks, net)]
        )
        key = validation_key(score, self.criterion)
        improved = key > self.best
        if improved:
            self.best = key
            save_checkpoint(self.best_path, dataclasses.replace(checkpoint, validation=score))
        self.validated_at = checkpoint.episode
        row = {
            "stage": checkpoint.stage,
            "episode": checkpoint.episode,
            "global_episode": checkpoint.global_episode,
            **dataclasses.asdict(score),
            "best": improved,
            "wall_time_s": wall_s,
        }
        self.sink.write([row])
        log.info(
            "validation at episode %d (%s): joint return %.2f, perfect %.0f%%%s",
            checkpoint.global_episode,
            checkpoint.stage,
            score.joint_return,
            100 * score.perfect_rate,
            " (best so far)" if improved else "",
        )


def _validation_groups(run: _Run, plan: StagePlan) -> list[tuple[MergeSite | None, list[EpisodeTask]]]:
    """The stage's held-out scenarios: on the run's net, or with ``[geometry]`` and its
    ``validation_geometries`` spread over that many merges drawn by the validation seed (their scenarios
    each from a seed of their own, scaled to their limits)."""
    config = run.config
    count = 0 if run.geometry is None else run.geometry.ranges.validation_geometries
    if run.geometry is None or count == 0:
        tasks = validation_tasks(
            plan.traffic,
            run.speed_limits,
            config.validation_scenarios,
            config.validation_seed,
            run.start_room,
            config.validation_limit_s,
        )
        return [(None, tasks)]
    rng = np.random.default_rng(config.validation_seed)
    groups: list[tuple[MergeSite | None, list[EpisodeTask]]] = []
    for i, scenarios in enumerate(split_evenly(config.validation_scenarios, count)):
        params, site = run.geometry.draw(rng)
        log.info("validation merge %d of %d: %s", i + 1, count, params)
        if scenarios:
            seed = config.validation_seed + 1 + i
            groups.append(
                (
                    site,
                    validation_tasks(
                        plan.traffic,
                        _site_limits(site),
                        scenarios,
                        seed,
                        start_room_m(site),
                        config.validation_limit_s,
                    ),
                )
            )
    return groups


def resumed_best(
    kept: list[dict[str, str]], best_path: Path, criterion: ValidationCriterion
) -> tuple[float, float]:
    """A resumed stage's best validation so far: its best checkpoint's own score, at full precision
    (validation.csv keeps 6 significant digits, so a later validation equal to the best would look better
    than the CSV's rounded value and replace the earliest of equals); the CSV's rows where there is no file."""
    saved = load_checkpoint(best_path).validation if best_path.is_file() else None
    if saved is not None:
        return validation_key(saved, criterion)
    return max(
        (validation_key(_score_of(r), criterion) for r in kept), default=(float("-inf"), float("-inf"))
    )


def _score_of(row: dict[str, str]) -> ValidationScore:
    """A validation.csv row's score."""
    return ValidationScore(**{f.name: float(row[f.name]) for f in dataclasses.fields(ValidationScore)})


def _train_stage(
    run: _Run,
    plan: StagePlan,
    learner: Learner,
    state: _RunState,
    workers: RolloutWorkers,
    metrics: MetricsSink,
    validation: _StageValidation | None,
    bar: Progress,
) -> None:
    """Rounds until the stage's budget is spent, their rows written. Ctrl-C saves a checkpoint of the
    completed rounds, then re-raises the stop (a KeyboardInterrupt, or an error raised from one)."""
    stage_bar = _StageBar(bar, plan, state.episode)
    fresh = state.global_episode == 0 and not run.latest.exists()

    def save() -> None:
        save_checkpoint(run.latest, state.checkpoint(learner, run.config, plan))

    try:
        if fresh:
            # A fresh run's starting point is a checkpoint too: a kill (even SIGKILL) before the first
            # periodic one then resumes from here to the weights of an uninterrupted run. Written during the
            # first round (nothing it holds changes before the round ends): the optimisers it builds import
            # torch._dynamo (about 1.3 CPU s, unless it was imported while the workers started), which should not
            # hold up the first episodes.
            workers.meanwhile(save)
        if validation is not None and validation.owed:
            validation.run(learner, state.checkpoint(learner, run.config, plan), run.wall_s())
            stage_bar.validated(validation.best_return)
        while state.episode < plan.episodes:
            stops.check()
            _round(run, plan, learner, state, workers, metrics, validation, stage_bar)
        workers.meanwhile(None)  # (none left for the next stage's first round)
    except BaseException as err:
        # A stop that arrives while a compiled kernel returns comes out as that call's SystemError, the
        # stop as its context: a stop all the same (``stops.behind``), so the completed rounds are saved.
        if stops.behind(err) is None:
            raise
        if not (fresh and state.global_episode == 0):
            save()
            log.warning("interrupted: saved %s at episode %d of %s", run.latest, state.episode, plan.name)
        elif not run.latest.exists():  # stopped in its first round before the starting checkpoint was written
            save()
        # (a fresh run stopped in its first round: its starting checkpoint says all there is)
        raise


def _round(
    run: _Run,
    plan: StagePlan,
    learner: Learner,
    state: _RunState,
    workers: RolloutWorkers,
    metrics: MetricsSink,
    validation: _StageValidation | None,
    stage_bar: _StageBar,
) -> None:
    """One round: collect episodes with the current actor, one update on them, their metrics rows;
    then a checkpoint and a validation when the round passed a multiple of ``checkpoint_every`` /
    ``validate_every`` episodes."""
    config = run.config
    if run.geometry is None:
        net, speed_limits, room, drawn = None, run.speed_limits, run.start_room, None
    else:
        # Drawn before the round's scenarios, from the same generator: a resumed run draws it again.
        drawn, site = run.geometry.draw(state.np_rng)
        net, speed_limits, room = site, _site_limits(site), start_room_m(site)
    tasks = state.ahead or _episode_tasks(run, plan, state, state.episode, speed_limits, room)
    counted = state.rng_states()
    if run.geometry is not None:
        run.geometry.prefetch(state.np_rng)
        state.ahead = []
    else:  # the next round's episodes (none at the stage's end), on the same net
        state.ahead = _episode_tasks(run, plan, state, state.episode + len(tasks), speed_limits, room)
        workers.load_ahead(state.ahead)
    stats, losses = workers.train_round(learner, tasks, net, central=plan.central)
    wall_s = run.wall_s()
    metrics.write(
        [
            {
                **_episode_row(plan, state.episode + i, state.global_episode + i, e),
                **losses,
                "wall_time_s": wall_s,
            }
            for i, e in enumerate(stats)
        ]
    )
    if run.geometry is not None and drawn is not None and net is not None:
        row = {"stage": plan.name, "episode": state.episode, "global_episode": state.global_episode}
        row |= {"episodes": len(tasks), **dataclasses.asdict(drawn), "net": Path(net.path).name}
        run.geometry.sink.write([row])
    before = state.global_episode
    state.advance(len(tasks), counted)
    stage_bar.episodes_done(state.episode, [s.success for s in stats])

    checkpoint_due = _passed_multiple(before, state.global_episode, config.checkpoint_every)
    validation_due = validation is not None and _passed_multiple(
        before, state.global_episode, config.validate_every
    )
    if checkpoint_due or validation_due:
        checkpoint = state.checkpoint(learner, config, plan)
        if checkpoint_due:
            save_checkpoint(run.latest, checkpoint)
            log.info("checkpoint at episode %d (%s)", state.global_episode, plan.name)
        if validation is not None and validation_due:
            validation.run(learner, checkpoint, run.wall_s())
            stage_bar.validated(validation.best_return)


def _site_limits(site: MergeSite) -> dict[Road, float]:
    """Each approach's own road's limit: what scenarios scale their start speeds by."""
    return {"main": site.main.road.speed_limit_mps, "merge": site.merge.road.speed_limit_mps}


def _episode_tasks(
    run: _Run,
    plan: StagePlan,
    state: _RunState,
    first: int,
    speed_limits: dict[Road, float],
    start_room: dict[Road, float] | None = None,
) -> list[EpisodeTask]:
    """The round's episodes from the stage's episode ``first`` (``episodes_per_update``, fewer at the stage's
    end, none after it): each a scenario on a net of ``speed_limits`` (the start speeds; the starts count from
    each road's start, so a road's length does not enter), then an action seed, drawn in that order from the
    run's generators."""
    n = min(run.config.episodes_per_update, plan.episodes - first)
    return [
        EpisodeTask(
            scenario=generate_scenario(
                state.np_rng,
                plan.traffic,
                speed_limits,
                name=f"{plan.name}-{first + i}",
                start_room_m=start_room,
            ),
            action_seed=int(torch.randint(0, 2**62, (1,), generator=state.torch_rng).item()),
        )
        for i in range(n)
    ]


def _passed_multiple(before: int, after: int, every: int) -> bool:
    """Whether counting from ``before`` to ``after`` passed a multiple of ``every``."""
    return after // every > before // every


def _episode_row(plan: StagePlan, episode: int, global_episode: int, s: EpisodeStats) -> dict[str, Any]:
    return {
        "stage": plan.name,
        "episode": episode,
        "global_episode": global_episode,
        "agents": s.agents,
        "return_mean": s.return_mean,
        **s.reward_parts,
        "success": s.success,
        "perfect": s.perfect,
        "collisions": s.collisions,
        "timed_out": s.timed_out,
        "length_steps": s.steps,
        "agent_steps": s.agent_steps,
        "sim_time_s": s.sim_time_s,
    }


def _finish_stage(
    run: _Run,
    plan: StagePlan,
    learner: Learner,
    state: _RunState,
    validation: _StageValidation | None,
) -> Path:
    """The stage's end: a last validation (unless its last round had one), then ``<stage>.pt`` and
    ``checkpoint.pt``. Returns ``<stage>.pt``."""
    checkpoint = state.checkpoint(learner, run.config, plan)
    if validation is not None and validation.validated_at != state.episode:
        validation.run(learner, checkpoint, run.wall_s())
    final = run.out_dir / f"{plan.name}.pt"
    save_checkpoint(final, checkpoint)
    save_checkpoint(run.latest, checkpoint)
    log.info("stage %s done: %d episodes, %s", plan.name, state.episode, final)
    return final


# --- the progress bar -------------------------------------------------------------------------------


def _make_progress(enabled: bool) -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[eps]:.2f} ep/s"),
        TextColumn("success {task.fields[success]:.0%}"),
        TextColumn("{task.fields[validation]}"),
        TimeRemainingColumn(),
        disable=not enabled,
        transient=False,
    )


class _StageBar:
    """One stage's line of the progress bar: episodes done, episodes per second, recent success rate."""

    def __init__(self, bar: Progress, plan: StagePlan, episode: int) -> None:
        self.bar = bar
        self.task = bar.add_task(
            plan.name, total=plan.episodes, completed=episode, eps=0.0, success=0.0, validation=""
        )
        self.recent: collections.deque[bool] = collections.deque(maxlen=SUCCESS_WINDOW)
        self.started, self.start_episode = time.perf_counter(), episode

    def episodes_done(self, episode: int, successes: Iterable[bool]) -> None:
        self.recent.extend(successes)
        rate = (episode - self.start_episode) / max(time.perf_counter() - self.started, 1e-9)
        self.bar.update(self.task, completed=episode, eps=rate, success=float(np.mean(self.recent)))

    def validated(self, best: float) -> None:
        self.bar.update(self.task, validation=f"best validation {best:.1f}")
