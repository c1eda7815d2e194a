"""The training loop, top to bottom: for each stage, collect episodes, update, log, checkpoint.

``run_training`` is what ``idas-sumo train`` calls. One round = ``episodes_per_update`` episodes
collected with the current actor (by 1 in-process worker or W processes), then one learner update
on all their agent-steps, then one metrics row per episode. Randomness: one numpy generator draws
the scenarios, one torch generator draws each episode's action-sampling seed; both are saved in
every checkpoint, so ``resume`` continues exactly where the last checkpoint left off.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import shutil
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any, get_args

import numpy as np
import torch
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from idas_sumo.agents.learner import Learner
from idas_sumo.agents.rollout import EpisodeData, batch_from_episodes
from idas_sumo.env.core import EnvConfig
from idas_sumo.env.scenario import Road, generate_scenario
from idas_sumo.errors import InputError
from idas_sumo.io_utils import ensure_writable_dir
from idas_sumo.sim.backend import require_display
from idas_sumo.sim.netgen import read_merge_net
from idas_sumo.training.checkpoint import TrainingCheckpoint, load_checkpoint, save_checkpoint
from idas_sumo.training.config import RESUME_FIELDS, Stage, TrainConfig
from idas_sumo.training.curriculum import StagePlan, plan_stages
from idas_sumo.training.metrics import METRICS_NAME, TENSORBOARD_DIR, MetricsSink
from idas_sumo.training.validation import VALIDATION_COLUMNS, score_episodes, validation_tasks
from idas_sumo.training.workers import EpisodeTask, RolloutWorkers, make_workers

__all__ = ["CHECKPOINT_NAME", "run_training", "stored_config"]

log = logging.getLogger(__name__)

CHECKPOINT_NAME = "checkpoint.pt"
"""The latest checkpoint of a run directory (what ``--resume`` reads)."""
VALIDATION_NAME = "validation.csv"
SUCCESS_WINDOW = 100  # episodes in the progress bar's running success rate


@dataclasses.dataclass
class _Counters:
    stage_index: int = 0
    episode: int = 0  # within the current stage
    global_episode: int = 0


def _payload(
    learner: Learner,
    config: TrainConfig,
    plan: StagePlan,
    counters: _Counters,
    np_rng_state: Mapping[str, Any],
    torch_rng_state: torch.Tensor,
) -> TrainingCheckpoint:
    return TrainingCheckpoint(
        learner=learner.state_dict(),
        config=config,
        stage=plan.name,
        stage_index=counters.stage_index,
        episode=counters.episode,
        global_episode=counters.global_episode,
        numpy_rng=dict(np_rng_state),
        torch_rng=torch_rng_state.clone(),
    )


def _episode_row(plan: StagePlan, episode: int, global_episode: int, e: EpisodeData) -> dict[str, Any]:
    s = e.stats
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


@dataclasses.dataclass
class _StageValidation:
    """One stage's held-out scenarios, its ``validation.csv`` sink and the best score so far."""

    workers: RolloutWorkers
    tasks: list[EpisodeTask]
    sink: MetricsSink
    best_path: Path
    best: float = float("-inf")
    validated_at: int = -1
    """The stage episode of the last validation."""

    def run(
        self,
        learner: Learner,
        plan: StagePlan,
        counters: _Counters,
        payload: TrainingCheckpoint,
        wall_s: float,
    ) -> None:
        """Score the greedy policy; save ``payload`` as ``best_path`` when it beats the best so far."""
        score = score_episodes([e.stats for e in self.workers.run(learner, self.tasks)])
        improved = score.joint_return > self.best
        if improved:
            self.best = score.joint_return
            save_checkpoint(self.best_path, dataclasses.replace(payload, validation=score))
        self.validated_at = counters.episode
        row = {
            "stage": plan.name,
            "episode": counters.episode,
            "global_episode": counters.global_episode,
            **dataclasses.asdict(score),
            "best": improved,
            "wall_time_s": wall_s,
        }
        self.sink.write([row])
        log.info(
            "validation at episode %d (%s): joint return %.2f, perfect %.0f%%%s",
            counters.global_episode,
            plan.name,
            score.joint_return,
            100 * score.perfect_rate,
            " (best so far)" if improved else "",
        )


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


def _run_outputs(out_dir: Path) -> list[Path]:
    """Every file or folder a training run writes into ``out_dir`` (what ``force`` replaces)."""
    stages = {plan.name for stage in get_args(Stage) for plan in plan_stages(TrainConfig(stage=stage))}
    names = [CHECKPOINT_NAME, METRICS_NAME, VALIDATION_NAME, TENSORBOARD_DIR]
    names += [f"{stage}{suffix}" for stage in sorted(stages) for suffix in (".pt", "_best.pt")]
    return [out_dir / name for name in names]


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


def run_training(
    net_path: Path | str,
    config: TrainConfig,
    out_dir: Path | str,
    resume: bool = False,
    progress: bool = True,
    gui: bool = False,
    force: bool = False,
) -> Path:
    """Train as ``config`` says; write checkpoints and ``metrics.csv`` under ``out_dir``.

    Returns the final checkpoint (``out_dir/<last stage>.pt``). ``resume`` continues the run in
    ``out_dir`` from its ``checkpoint.pt`` with the saved config, taking only ``RESUME_FIELDS``
    (workers, the stage budgets) from ``config``: a larger budget extends a finished run. Without
    ``resume``, an ``out_dir`` that holds files is refused unless ``force``, which replaces the
    files a run writes. ``gui`` shows the rollouts in sumo-gui (one worker only). Ctrl-C saves a
    checkpoint of the completed rounds, then re-raises KeyboardInterrupt.
    """
    net_path = Path(net_path)
    out_dir = Path(out_dir)
    latest = out_dir / CHECKPOINT_NAME
    if not net_path.is_file():
        raise InputError(f"{net_path}: network file not found")
    if gui and config.workers > 1:
        raise InputError("--gui needs --workers 1")
    require_display(gui)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir}: exists and is not a directory")
    if resume and force:
        raise InputError("--resume and --force exclude each other")
    resumed: TrainingCheckpoint | None = None
    if resume:
        if not latest.exists():
            raise InputError(f"{latest}: no checkpoint to resume from")
        resumed = load_checkpoint(latest)
        config = _resumed_config(resumed.config, config)
    elif not force and out_dir.is_dir() and any(out_dir.iterdir()):
        if latest.exists():
            raise InputError(
                f"{out_dir}: already holds a training run; pass --resume to continue it, --force to "
                "start over, or choose another --out"
            )
        raise InputError(
            f"--out {out_dir}: directory exists and is not empty (use --force to overwrite its files)"
        )
    if config.init_from and resumed is None:
        try:
            init_state = load_checkpoint(config.init_from).learner
        except InputError as err:
            raise InputError(
                f"init_from: {err} (a path from the working directory; the shipped recipe makes "
                "runs/imitation.pt with scripts/pretrain_imitation.py)"
            ) from None
    else:
        init_state = None
    ensure_writable_dir(out_dir)

    plans = plan_stages(config)
    net = read_merge_net(net_path)
    limits: dict[Road, float] = {"main": net.main.speed_limit_mps, "merge": net.merge.speed_limit_mps}
    env_config = EnvConfig(max_episode_s=config.max_episode_s, reward=config.reward)

    np_rng = np.random.default_rng(config.seed)
    torch_rng = torch.Generator().manual_seed(config.seed)
    counters = _Counters()
    if resumed is not None:
        if resumed.stage_index >= len(plans) or plans[resumed.stage_index].name != resumed.stage:
            raise InputError(f"{latest}: stage {resumed.stage!r} does not belong to this run's plan")
        budget = plans[resumed.stage_index].episodes
        if resumed.episode > budget:
            raise InputError(
                f"{latest}: the run is at episode {resumed.episode} of stage {resumed.stage!r}; "
                f"a budget of {budget} episodes ends before that (give --episodes {resumed.episode} "
                "or more)"
            )
        np_rng.bit_generator.state = resumed.numpy_rng
        torch_rng.set_state(resumed.torch_rng)
        counters = _Counters(resumed.stage_index, resumed.episode, resumed.global_episode)
        _drop_best_after(out_dir, counters.global_episode)
    elif force:
        for path in _run_outputs(out_dir):
            if path.is_dir():
                shutil.rmtree(path)
            else:
                path.unlink(missing_ok=True)

    show = progress and sys.stderr.isatty()
    started = time.perf_counter()
    final = latest
    learner: Learner | None = None
    with (
        make_workers(net_path, env_config, config.seed, config.workers, gui=gui) as workers,
        # On resume, rows past the checkpoint go: an episode row is stamped with its own index, a
        # validation row with the episode count it was scored at (one at the checkpoint's count stays).
        MetricsSink(out_dir, counters.global_episode if resumed else None) as sink,
        (
            MetricsSink(
                out_dir,
                counters.global_episode + 1 if resumed else None,
                name=VALIDATION_NAME,
                columns=VALIDATION_COLUMNS,
                tensorboard_keys=(),
            )
            if config.validate_every
            else contextlib.nullcontext()
        ) as validation_sink,
        _make_progress(show) as bar,
    ):
        for stage_index in range(counters.stage_index, len(plans)):
            plan = plans[stage_index]
            previous = learner
            learner = Learner(plan.learner, seed=config.seed + stage_index)
            if resumed is not None and stage_index == resumed.stage_index:
                learner.load_state_dict(resumed.learner)
            elif plan.init_from_previous and previous is not None:
                learner.load_state_dict(previous.state_dict(), load_optimisers=False)
            elif init_state is not None and stage_index == 0:
                learner.load_state_dict(init_state, load_optimisers=False)
            if stage_index != counters.stage_index:
                counters = _Counters(stage_index, 0, counters.global_episode)
            task = bar.add_task(
                plan.name,
                total=plan.episodes,
                completed=counters.episode,
                eps=0.0,
                success=0.0,
                validation="",
            )
            recent: collections.deque[bool] = collections.deque(maxlen=SUCCESS_WINDOW)
            validation = None
            if validation_sink is not None:
                best_path = out_dir / f"{plan.name}_best.pt"
                validation = _StageValidation(
                    workers,
                    validation_tasks(
                        plan.traffic, limits, config.validation_scenarios, config.validation_seed
                    ),
                    validation_sink,
                    best_path,
                )
                if resumed is not None and stage_index == resumed.stage_index:
                    # The stage's validations before the checkpoint: the best so far, and whether the
                    # checkpoint's own episode was validated already (then not twice).
                    kept = [r for r in validation_sink.kept if r["stage"] == plan.name]
                    validation.best = max((float(r["joint_return"]) for r in kept), default=float("-inf"))
                    if kept and int(kept[-1]["episode"]) == counters.episode:
                        validation.validated_at = counters.episode
            stage_start, stage_start_episode = time.perf_counter(), counters.episode
            round_rng = (np_rng.bit_generator.state, torch_rng.get_state())
            try:
                while counters.episode < plan.episodes:
                    # The RNG state at the start of a round is what a checkpoint of complete work holds.
                    round_rng = (np_rng.bit_generator.state, torch_rng.get_state())
                    n = min(config.episodes_per_update, plan.episodes - counters.episode)
                    tasks = [
                        EpisodeTask(
                            scenario=generate_scenario(
                                np_rng, plan.traffic, limits, name=f"{plan.name}-{counters.episode + i}"
                            ),
                            action_seed=int(torch.randint(0, 2**62, (1,), generator=torch_rng).item()),
                        )
                        for i in range(n)
                    ]
                    episodes = workers.run(learner, tasks)
                    losses = learner.update(batch_from_episodes(episodes, central=plan.central))

                    wall = time.perf_counter() - started
                    rows = []
                    for i, e in enumerate(episodes):
                        row = _episode_row(plan, counters.episode + i, counters.global_episode + i, e)
                        rows.append({**row, **losses, "wall_time_s": wall})
                        recent.append(e.stats.success)
                    sink.write(rows)
                    before = counters.global_episode
                    counters.episode += n
                    counters.global_episode += n
                    rate = (counters.episode - stage_start_episode) / max(
                        time.perf_counter() - stage_start, 1e-9
                    )
                    bar.update(task, completed=counters.episode, eps=rate, success=float(np.mean(recent)))
                    checkpoint_due = (
                        counters.global_episode // config.checkpoint_every > before // config.checkpoint_every
                    )
                    validation_due = validation is not None and (
                        counters.global_episode // config.validate_every > before // config.validate_every
                    )
                    if checkpoint_due or validation_due:
                        payload = _payload(
                            learner, config, plan, counters, np_rng.bit_generator.state, torch_rng.get_state()
                        )
                        if checkpoint_due:
                            save_checkpoint(latest, payload)
                            log.info("checkpoint at episode %d (%s)", counters.global_episode, plan.name)
                        if validation is not None and validation_due:
                            validation.run(learner, plan, counters, payload, time.perf_counter() - started)
                            bar.update(task, validation=f"best validation {validation.best:.1f}")
            except KeyboardInterrupt:
                # Save the completed rounds: the RNG as it was before the interrupted round's draws.
                save_checkpoint(latest, _payload(learner, config, plan, counters, *round_rng))
                log.warning("interrupted: saved %s at episode %d of %s", latest, counters.episode, plan.name)
                raise
            payload = _payload(
                learner, config, plan, counters, np_rng.bit_generator.state, torch_rng.get_state()
            )
            if validation is not None and validation.validated_at != counters.episode:
                validation.run(learner, plan, counters, payload, time.perf_counter() - started)
            final = out_dir / f"{plan.name}.pt"
            save_checkpoint(final, payload)
            save_checkpoint(latest, payload)
            log.info("stage %s done: %d episodes, %s", plan.name, counters.episode, final)
    return final
