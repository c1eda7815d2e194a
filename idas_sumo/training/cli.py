"""``idas-sumo train``: turn the parsed flags into a TrainConfig and call ``run_training``."""

from __future__ import annotations

import argparse
from pathlib import Path

from idas_sumo.resources import DEFAULT_TRAIN_CONFIG
from idas_sumo.training.checkpoint import load_checkpoint
from idas_sumo.training.config import TrainConfig, load_train_config
from idas_sumo.training.loop import CHECKPOINT_NAME, run_training, stored_config

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
    )


def train_from_args(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    out = Path(getattr(args, "out", None) or Path("runs") / config.stage)
    resume = bool(getattr(args, "resume", False))
    if resume and (out / CHECKPOINT_NAME).is_file():
        # The run's own config is the base, so that only what the user typed can differ from it.
        config = config_from_args(args, base=stored_config(out))
    final = run_training(
        Path(args.net),
        config,
        out,
        resume=resume,
        progress=not getattr(args, "no_progress", False),
        gui=bool(getattr(args, "gui", False)),
        force=bool(getattr(args, "force", False)),
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
