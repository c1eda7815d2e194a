"""The checkpoint file: what makes a file one of ours, reading it safely, and the actor in it.

A checkpoint (written by ``training.checkpoint.save_checkpoint``) is a dict of plain types and
tensors. Its own keys are kind, format, package_version, obs_layout_id and learner
(``Learner.state_dict()``); the rest (training progress, config) is training's, checked by
``training.checkpoint.load_checkpoint``. Shipped policies are such files, and evaluation needs only
their actor, so reading lives here, below training and evaluation alike.

Files are read with ``torch.load(weights_only=True)``, so pickled code never runs. Every problem
(missing, empty, truncated, not ours, other layout, non-finite weights) is one ``InputError`` line
naming the file.
"""

from __future__ import annotations

import pickle
import warnings
from pathlib import Path
from typing import Any

import torch

from idas_sumo.agents.learner import Learner, LearnerConfig
from idas_sumo.env.layout import OBS_LAYOUT_ID
from idas_sumo.errors import InputError

__all__ = ["CHECKPOINT_KIND", "TRAIN_CHECKPOINT_FORMAT", "load_actor", "read_checkpoint_file"]

CHECKPOINT_KIND = "idas-sumo-train"
TRAIN_CHECKPOINT_FORMAT = 1
NETWORK_KEYS = ("actor", "value", "central", "value_target", "central_target")


def read_checkpoint_file(path: Path | str) -> dict[str, Any]:
    """Read a checkpoint file and check what every checkpoint has: ours, this format and layout, sound weights."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: checkpoint not found")
    if p.is_dir():
        raise InputError(f"{p}: is a directory, expected a checkpoint file")
    if p.stat().st_size == 0:
        raise InputError(f"{p}: empty file, not a checkpoint")
    try:
        with warnings.catch_warnings():
            # torch warns on stderr about pickle protocols it did not write; the error below says it all.
            warnings.simplefilter("ignore")
            data = torch.load(p, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        raise InputError(f"{p}: {_refused_pickle_reason(err)}") from None
    except Exception as err:  # any file: torch raises RuntimeError, KeyError, EOFError, ...
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise InputError(f"{p}: not a readable checkpoint (truncated or corrupt?): {first[:200]}") from None
    if not isinstance(data, dict) or data.get("kind") != CHECKPOINT_KIND:
        raise InputError(f"{p}: not an idas-sumo training checkpoint")
    if data.get("format") != TRAIN_CHECKPOINT_FORMAT:
        raise InputError(
            f"{p}: checkpoint format {data.get('format')!r}, this build reads {TRAIN_CHECKPOINT_FORMAT}"
        )
    if data.get("obs_layout_id") != OBS_LAYOUT_ID:
        raise InputError(
            f"{p}: written for observation layout {data.get('obs_layout_id')!r}, "
            f"this build uses {OBS_LAYOUT_ID!r}"
        )
    learner = data.get("learner")
    if not isinstance(learner, dict) or any(not isinstance(learner.get(k), dict) for k in NETWORK_KEYS):
        raise InputError(f"{p}: checkpoint has no complete learner weights")
    for net in NETWORK_KEYS:
        for name, tensor in learner[net].items():
            if not isinstance(tensor, torch.Tensor):
                raise InputError(f"{p}: {net}.{name} is not a tensor")
            if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
                raise InputError(f"{p}: non-finite weights in {net}.{name}")
    return data


def _refused_pickle_reason(err: pickle.UnpicklingError) -> str:
    """One line for a file ``weights_only`` refused: torch's own text advises ``weights_only=False``."""
    text = str(err).strip()
    if not text.startswith("Weights only load failed"):
        first = text.splitlines()[0] if text else type(err).__name__
        return f"not a readable checkpoint (truncated or corrupt?): {first[:200]}"
    details = [
        line.split("WeightsUnpickler error:")[-1].strip()
        for line in text.splitlines()[1:]
        if line.strip() and not line.startswith("Check the documentation")
    ]
    details = [d for d in details if d]
    reason = f" ({details[0][:160]})" if details else ""
    return (
        "not a checkpoint: it holds Python objects other than tensors and plain data, "
        f"which are never unpickled{reason}"
    )


def load_actor(path: Path | str) -> Learner:
    """A checkpoint's networks in a ``Learner`` (use its ``act``); no optimiser state, for evaluation."""
    data = read_checkpoint_file(path)
    learner = Learner(LearnerConfig(), seed=0)
    try:
        learner.load_state_dict(data["learner"], load_optimisers=False)
    except (RuntimeError, KeyError) as err:  # shapes or names that do not fit these networks
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise InputError(f"{path}: weights do not fit this build's networks: {first[:200]}") from None
    except InputError as err:
        raise InputError(f"{path}: {err}") from None
    return learner
