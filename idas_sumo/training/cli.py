"""``idas-sumo train``: turn the parsed flags into a TrainConfig and call ``run_training``."""

from __future__ import annotations

import argparse
from pathlib import Path

from idas_sumo.distributed import LOCAL
from idas_sumo.env.net_needs import check_road_lengths, road_needs
from idas_sumo.errors import InputError
from idas_sumo.resources import DEFAULT_TRAIN_CONFIG
from idas_sumo.sim.merge_detect import MergeSite, choose_merge
from idas_sumo.sim.processes import SEED_LIMIT, max_workers
from idas_sumo.training.checkpoint import load_checkpoint
from idas_sumo.training.config import TrainConfig, load_train_config
from idas_sumo.training.loop import CHECKPOINT_NAME, run_training, stored_config
from idas_sumo.training.metrics import METRICS_NAME

__all__ = ["config_from_args", "train_from_args"]


def config_from_args(args: argparse.Namespace, base: TrainConfig | None = None) -> TrainConfig:
    """The flags on top of their base: ``--config`` if given, else ``base`` (a resumed run's own
    config), else the shipped default, else built-in defaults."""
    path: Path | None = getattr(args, "config", None)
    if path is not None:
        base = load_train_config(path)
    elif base is None:
        base = load_train_config(DEFAULT_TRAIN_CONFIG) if DEFAULT_TRAIN_CONFIG.is_file() else TrainConfig()
    return base.with_overrides(
        stage=getattr(args, "stage", None),
        episodes=getattr(args, "episodes", None),
        workers=getattr(args, "workers", None),
        seed=getattr(args, "seed", None),
        copies=getattr(args, "copies", None),
        safety_mask=getattr(args, "safety_mask", None),
        junction=getattr(args, "junction", None),
    )


def _check_run(args: argparse.Namespace, config: TrainConfig, source: str) -> MergeSite:
    """What the config's own checks cannot know: this machine's CPUs, SUMO's seed range, and whether
    the net's roads fit the run's traffic (env/net_needs.py); the run's merge site (the one parse of
    the net). ``source`` names where the values came from (a flag's value was checked by argparse)."""
    if not 0 <= config.seed < SEED_LIMIT:
        raise InputError(
            f"{source}: seed must be in [0, {SEED_LIMIT}) (SUMO's seed range), got {config.seed}"
        )
    limit = max_workers()
    # Ray actors on a cluster are bound by its CPUs, not this machine's (distributed/ray_pool.py).
    if config.workers > limit and getattr(args, "ray_address", None) in (None, LOCAL):
        raise InputError(
            f"{source}: workers = {config.workers} is more than this machine's {limit} CPUs "
            f"(pass --workers {limit} or fewer)"
        )
    start_range = max(config.robot_traffic.start_range_m, config.intelligent_traffic.start_range_m)
    site = choose_merge(Path(args.net), config.env.junction)
    check_road_lengths(site, road_needs(start_range, config.longest_episode_s, source))
    return site


def train_from_args(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    source = str(getattr(args, "config", None) or DEFAULT_TRAIN_CONFIG)
    out = Path(getattr(args, "out", None) or Path("runs") / config.stage)
    resume = bool(getattr(args, "resume", False))
    if resume and not (out / CHECKPOINT_NAME).is_file() and (out / METRICS_NAME).is_file():
        # Killed before its first checkpoint: its config was never saved, so --resume alone cannot
        # know what to continue; the same command with --force runs it again from the start.
        raise InputError(
            f"{out}: the run stopped before its first checkpoint, so there is nothing to resume; "
            "start it over with the same flags and --force"
        )
    if resume and (out / CHECKPOINT_NAME).is_file():
        # The run's own config is the base, so that only what the user typed can differ from it.
        config = config_from_args(args, base=stored_config(out))
        source = str(out / CHECKPOINT_NAME)
    site = _check_run(args, config, source)
    final = run_training(
        site,
        config,
        out,
        resume=resume,
        progress=not getattr(args, "no_progress", False),
        gui=bool(getattr(args, "gui", False)),
        force=bool(getattr(args, "force", False)),
        ray_address=getattr(args, "ray_address", None),
    )
    print(f"wrote {final}")
    for best in sorted(out.glob("*_best.pt")):
        saved = load_checkpoint(best)
        score = saved.validation
        if score is not None:
            print(
                f"wrote {best}: best on validation at {saved.stage} episode {saved.episode} "
                f"(joint return {score.joint_return:.2f}, perfect {score.perfect_rate:.0%})"
            )
    return 0
