"""``idas-sumo train``: turn the parsed flags into a TrainConfig and call ``run_training``."""

from __future__ import annotations

import argparse
from pathlib import Path

from idas_sumo.resources import DEFAULT_TRAIN_CONFIG
from idas_sumo.training.checkpoint import load_checkpoint
from idas_sumo.training.config import TrainConfig, load_train_config
from idas_sumo.training.loop import run_training

__all__ = ["config_from_args", "train_from_args"]


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """The TOML (``--config``, else the shipped default, else built-in defaults) with the flags on top."""
    path: Path | None = getattr(args, "config", None)
    if path is not None:
        base = load_train_config(path)
    elif DEFAULT_TRAIN_CONFIG.is_file():
        base = load_train_config(DEFAULT_TRAIN_CONFIG)
    else:
        base = TrainConfig()
    return base.with_overrides(
        stage=getattr(args, "stage", None),
        episodes=getattr(args, "episodes", None),
        workers=getattr(args, "workers", None),
        seed=getattr(args, "seed", None),
    )


def train_from_args(args: argparse.Namespace) -> int:
    config = config_from_args(args)
    out = getattr(args, "out", None) or Path("runs") / config.stage
    final = run_training(
        Path(args.net),
        config,
        Path(out),
        resume=bool(getattr(args, "resume", False)),
        progress=not getattr(args, "no_progress", False),
        gui=bool(getattr(args, "gui", False)),
    )
    print(f"wrote {final}")
    for best in sorted(Path(out).glob("*_best.pt")):
        saved = load_checkpoint(best)
        score = saved["validation"]
        print(
            f"wrote {best}: best on validation at {saved['stage']} episode {saved['episode']} "
            f"(joint return {score['joint_return']:.2f}, perfect {score['perfect_rate']:.0%})"
        )
    return 0
