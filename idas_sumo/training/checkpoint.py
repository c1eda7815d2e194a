"""Training checkpoints: the typed state of a run, written atomically, read and checked.

``TrainingCheckpoint`` is ``agents.checkpoint_file.PolicyCheckpoint`` (the learner's state, package
version, observation layout) plus where the run stands: its config, stage, episode counts, the RNG
states that make ``--resume`` continue exactly, and for a ``<stage>_best.pt`` the validation score
that picked it. ``PolicyCheckpoint.to_dict`` / ``from_dict`` turn it into / from the dict on disk.

Every problem reading one (missing, empty, truncated, not ours, other layout, missing or ill-typed
values, non-finite weights) is one ``InputError`` line naming the file.
"""

from __future__ import annotations

import dataclasses
import io
import os
from pathlib import Path
from typing import Any

import torch

from idas_sumo.agents.checkpoint_file import PolicyCheckpoint
from idas_sumo.io_utils import atomic_open
from idas_sumo.training.config import TrainConfig
from idas_sumo.training.validation import ValidationScore

__all__ = ["TrainingCheckpoint", "config_as_it_ran", "load_checkpoint", "save_checkpoint"]


@dataclasses.dataclass(frozen=True, kw_only=True, eq=False)
class TrainingCheckpoint(PolicyCheckpoint):
    """A run's state after a whole number of rounds: enough to continue it exactly."""

    config: TrainConfig
    """The run's own config (``--resume`` continues with it)."""
    stage: str
    """The name of the stage the run is in (a ``StagePlan`` name)."""
    stage_index: int
    """Its index in the run's plan (``plan_stages(config)``)."""
    episode: int
    """Episodes completed in this stage."""
    global_episode: int
    """Episodes completed in every stage of the run."""
    numpy_rng: dict[str, Any]
    """The scenario generator's bit-generator state."""
    torch_rng: torch.Tensor
    """The action-seed generator's state (a uint8 tensor)."""
    validation: ValidationScore | None = None
    """For a ``<stage>_best.pt``: the held-out score that made these the best weights."""

    @classmethod
    def from_dict(cls, data: Any, path: Path) -> TrainingCheckpoint:
        """As ``PolicyCheckpoint.from_dict``; a run saved before a default changed reads as it ran, so a resumed
        run goes on as it did: before ``[learner] q_horizon`` existed Q was trained along each agent's own steps
        ('agent'), before ``entries`` existed later entries were drawn 'as_drawn'."""
        config = data.get("config") if isinstance(data, dict) else None
        if isinstance(config, dict):
            data = {**data, "config": config_as_it_ran(config)}
        return super().from_dict(data, path)


_PREDATED_SETTINGS = (
    ("learner", "q_horizon", "agent"),
    ("robot_traffic", "entries", "as_drawn"),
    ("intelligent_traffic", "entries", "as_drawn"),
)
"""(section, key, the value a run used before the key existed) for each setting whose default changed."""


def config_as_it_ran(config: dict[str, Any]) -> dict[str, Any]:
    """``config`` with the values of settings it predates: what the run used before they existed."""
    config = dict(config)
    for section, key, value in _PREDATED_SETTINGS:
        table = config.get(section)
        if isinstance(table, dict) and key not in table:
            config[section] = {**table, key: value}
    return config


def save_checkpoint(path: Path, checkpoint: PolicyCheckpoint) -> None:
    """Write ``checkpoint`` to ``path`` atomically: temp file in the same directory, fsync, rename.

    torch serialises into memory first (a few MB) and the bytes are written with an ordinary write:
    torch writing to a file itself turns a full disk into a ``RuntimeError`` ("unexpected pos …",
    from its zip writer's position check) that names neither the disk nor the file. This way a full
    disk is the ``OSError`` it is, naming ``path``; the temp file is removed and the previous
    checkpoint is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    torch.save(checkpoint.to_dict(), buffer)
    try:
        with atomic_open(path, "wb") as f:
            f.write(buffer.getbuffer())
    except OSError as err:
        raise OSError(err.errno, err.strerror or str(err), str(path)) from None
    try:  # make the rename itself durable
        dir_fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dir_fd)
    except OSError:
        pass
    finally:
        os.close(dir_fd)


def load_checkpoint(path: Path | str) -> TrainingCheckpoint:
    """Read and check a training checkpoint (``--resume``, ``init_from``, a ``<stage>_best.pt``)."""
    return TrainingCheckpoint.read(path)
