"""Training checkpoints: written atomically, read through ``agents.checkpoint_file``, checked.

A checkpoint is a dict of plain types and tensors::

    kind, format, package_version, obs_layout_id, learner (Learner.state_dict()),
    config (TrainConfig as a dict), stage, stage_index, episode (within the stage),
    global_episode, numpy_rng (bit-generator state), torch_rng (uint8 tensor)

Every problem reading one (missing, empty, truncated, not ours, other layout, non-finite weights)
is one ``InputError`` line naming the file.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import torch

from idas_sumo import __version__
from idas_sumo.agents.checkpoint_file import CHECKPOINT_KIND, TRAIN_CHECKPOINT_FORMAT, read_checkpoint_file
from idas_sumo.env.layout import OBS_LAYOUT_ID
from idas_sumo.errors import InputError
from idas_sumo.io_utils import atomic_open

__all__ = ["load_checkpoint", "save_checkpoint"]


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """Write ``payload`` to ``path`` atomically: temp file in the same directory, fsync, rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    full = {
        "kind": CHECKPOINT_KIND,
        "format": TRAIN_CHECKPOINT_FORMAT,
        "package_version": __version__,
        "obs_layout_id": OBS_LAYOUT_ID,
        **payload,
    }
    with atomic_open(path, "wb") as f:
        torch.save(full, f)
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


def load_checkpoint(path: Path | str) -> dict[str, Any]:
    """Read and check a training checkpoint: the file (``read_checkpoint_file``), then its training state."""
    p = Path(path)
    data = read_checkpoint_file(p)
    for key in ("stage", "stage_index", "episode", "global_episode", "config"):
        if key not in data:
            raise InputError(f"{p}: checkpoint lacks {key!r}")
    for key in ("episode", "global_episode", "stage_index"):
        value = data[key]
        if not isinstance(value, int) or value < 0 or (isinstance(value, float) and not math.isfinite(value)):
            raise InputError(f"{p}: {key} must be a non-negative integer, got {value!r}")
    return data
