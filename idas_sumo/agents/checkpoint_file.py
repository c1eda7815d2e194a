"""The checkpoint file: its typed contents, turning them into / from the dict on disk, reading safely.

On disk a checkpoint is the flat dict ``torch.save`` wrote: ``kind`` and ``format`` (what makes the
file ours, and which format) plus one key per field of the checkpoint dataclass, under the field's
own name. ``PolicyCheckpoint`` holds what every checkpoint has and evaluation reads (the learner's
state, the package version and observation layout it was written for);
``training.checkpoint.TrainingCheckpoint`` adds the training state. ``PolicyCheckpoint.to_dict`` and
``from_dict`` are the one place that turns either into / from that dict, so no key is spelled
elsewhere. Shipped policies are such files, and evaluation needs only their actor, so reading lives
here, below training and evaluation alike.

Files are read with ``torch.load(weights_only=True)``, so pickled code never runs. Every problem
(missing, empty, truncated, not ours, other layout, missing or ill-typed values, non-finite weights,
a checksum that does not match) is one ``InputError`` line naming the file.

Checksums: torch's zip container does not check its data, so a flipped byte in a tensor loaded as
different weights without a word. A checkpoint therefore carries ``content_sha256``, the SHA-256 of
everything else it holds (every tensor's dtype, shape and bytes, every plain value), checked on load.
Files written before that have none: they are checked against ``file_sha256`` (of the whole file, as
``sha256sum`` prints it) in the ``<name>.json`` metadata beside them when there is one (the shipped
policies), and otherwise load with a warning.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import pickle
import types
import typing
import warnings
from pathlib import Path
from typing import Any, Self

import torch

from idas_sumo import __version__
from idas_sumo.agents.learner import Learner, LearnerConfig
from idas_sumo.config import from_dict, to_plain
from idas_sumo.env.layout import OBS_LAYOUT_ID
from idas_sumo.errors import InputError
from idas_sumo.io_utils import file_digest

__all__ = [
    "CHECKPOINT_KIND",
    "CHECKSUM_KEY",
    "TRAIN_CHECKPOINT_FORMAT",
    "PolicyCheckpoint",
    "content_digest",
    "load_actor",
]

log = logging.getLogger(__name__)

CHECKPOINT_KIND = "idas-sumo-train"
TRAIN_CHECKPOINT_FORMAT = 1
NETWORK_KEYS = ("actor", "value", "central", "value_target", "central_target")
CHECKSUM_KEY = "content_sha256"
"""The key of a checkpoint's own checksum (``content_digest`` of the rest of its dict)."""
SIDECAR_CHECKSUM_KEY = "file_sha256"
"""The key of a whole-file checksum in the ``<name>.json`` beside an older checkpoint."""


@dataclasses.dataclass(frozen=True, kw_only=True, eq=False)  # eq=False: tensors have no plain ==
class PolicyCheckpoint:
    """What every checkpoint holds: the learner's state and the build that wrote it.

    A subclass adds fields; each is saved under its own name. A field that may be ``None`` may be
    absent from a file (and ``None`` is not written); every other field must be there.
    """

    learner: dict[str, Any]
    """``Learner.state_dict()``: the networks, their targets and the optimisers' states."""
    package_version: str = __version__
    """The idas-sumo version that wrote the file (recorded, not checked)."""
    obs_layout_id: str = OBS_LAYOUT_ID
    """The observation layout the actor was trained on; a file of another layout is refused."""

    def to_dict(self) -> dict[str, Any]:
        """The dict ``torch.save`` writes: plain types and tensors only, so ``weights_only`` reads it."""
        data: dict[str, Any] = {"kind": CHECKPOINT_KIND, "format": TRAIN_CHECKPOINT_FORMAT}
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if value is None:
                continue
            if dataclasses.is_dataclass(value) and not isinstance(value, type):
                value = to_plain(value)
            data[field.name] = value
        data[CHECKSUM_KEY] = content_digest(data)
        return data

    @classmethod
    def from_dict(cls, data: Any, path: Path) -> Self:
        """The checkpoint in ``data`` (what ``torch.load`` returned for ``path``), every value checked;
        keys of fields ``cls`` lacks (a training checkpoint read as a policy) are ignored."""
        if not isinstance(data, dict) or data.get("kind") != CHECKPOINT_KIND:
            raise InputError(f"{path}: not an idas-sumo training checkpoint")
        if data.get("format") != TRAIN_CHECKPOINT_FORMAT:
            raise InputError(
                f"{path}: checkpoint format {data.get('format')!r}, this build reads {TRAIN_CHECKPOINT_FORMAT}"
            )
        hints = typing.get_type_hints(cls)
        values: dict[str, Any] = {}
        for field in dataclasses.fields(cls):
            if field.name in data:
                values[field.name] = _checked(data[field.name], hints[field.name], f"{path}: {field.name}")
            elif not _optional(hints[field.name]):
                raise InputError(f"{path}: checkpoint lacks {field.name!r}")
        checkpoint = cls(**values)
        checkpoint._check(path)
        return checkpoint

    @classmethod
    def read(cls, path: Path | str) -> Self:
        """Read and check the checkpoint file at ``path`` (its values, then its checksum: an
        ill-typed value is named as such even in a file that was edited)."""
        p = Path(path)
        data = _load_file(p)
        checkpoint = cls.from_dict(data, p)
        _verify_checksum(data, p)
        return checkpoint

    def _check(self, path: Path) -> None:
        """What the types alone do not say: the layout matches this build, the weights are sound."""
        if self.obs_layout_id != OBS_LAYOUT_ID:
            raise InputError(
                f"{path}: written for observation layout {self.obs_layout_id!r}, "
                f"this build uses {OBS_LAYOUT_ID!r}"
            )
        if any(not isinstance(self.learner.get(k), dict) for k in NETWORK_KEYS):
            raise InputError(f"{path}: checkpoint has no complete learner weights")
        for net in NETWORK_KEYS:
            for name, tensor in self.learner[net].items():
                if not isinstance(tensor, torch.Tensor):
                    raise InputError(f"{path}: {net}.{name} is not a tensor")
                if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
                    raise InputError(f"{path}: non-finite weights in {net}.{name}")


def _optional(annotation: Any) -> bool:
    return typing.get_origin(annotation) in (typing.Union, types.UnionType) and type(None) in typing.get_args(
        annotation
    )


def _checked(value: Any, annotation: Any, where: str) -> Any:
    """``value`` as a field of type ``annotation`` (a dataclass from its dict), or an InputError."""
    if _optional(annotation):
        if value is None:
            return None
        (annotation,) = [a for a in typing.get_args(annotation) if a is not type(None)]
    if dataclasses.is_dataclass(annotation):
        try:
            return from_dict(typing.cast(type, annotation), value, where)
        except InputError as err:  # a dataclass's own range checks do not name the file
            raise err if str(err).startswith(where) else InputError(f"{where}: {err}") from None
    if annotation is int:  # the counts of training progress
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise InputError(f"{where} must be a non-negative integer, got {value!r}")
        return value
    expected = typing.get_origin(annotation) or annotation  # dict[str, Any] -> dict
    if not isinstance(value, expected):
        raise InputError(f"{where} must be a {expected.__name__}, got {type(value).__name__}")
    return value


def content_digest(data: dict[str, Any]) -> str:
    """The SHA-256 (hex) of a checkpoint dict without its ``CHECKSUM_KEY``: tensors by dtype, shape
    and bytes, containers by their items (dict keys in a fixed order), plain values by type and repr,
    so that the dict ``torch.save`` wrote and the one ``torch.load`` returns give the same digest."""
    h = hashlib.sha256()

    def feed(value: Any) -> None:
        if isinstance(value, torch.Tensor):
            t = value.detach().cpu().contiguous().reshape(-1)
            h.update(f"T{t.dtype}{tuple(value.shape)}:".encode())
            h.update(t.view(torch.uint8).numpy().tobytes())
        elif isinstance(value, dict):
            h.update(f"D{len(value)}:".encode())
            for key in sorted(value, key=repr):
                feed(key)
                feed(value[key])
        elif isinstance(value, list | tuple):
            h.update(f"{type(value).__name__}{len(value)}:".encode())
            for item in value:
                feed(item)
        else:
            h.update(f"{type(value).__name__}:{value!r};".encode())

    feed({k: v for k, v in data.items() if k != CHECKSUM_KEY})
    return h.hexdigest()


_DAMAGED = "checksum mismatch: the file was changed or damaged after it was written"


def _verify_checksum(data: dict[str, Any], p: Path) -> None:
    """Compare the checkpoint's own checksum, else its metadata's; an older file without either loads
    with a warning (it predates checksums: nothing to compare with)."""
    stored = data.get(CHECKSUM_KEY)
    if stored is not None:
        if not isinstance(stored, str) or stored != content_digest(data):
            raise InputError(f"{p}: {_DAMAGED} (its {CHECKSUM_KEY} does not match its contents)")
        return
    sidecar = p.with_name(p.name.removesuffix(".pt") + ".json")
    expected = _sidecar_checksum(sidecar)
    if expected is None:
        log.warning("%s: no checksum (written before checkpoints carried one); loaded unverified", p)
    elif file_digest(p) != expected:
        raise InputError(f"{p}: {_DAMAGED} (its SHA-256 differs from {SIDECAR_CHECKSUM_KEY} in {sidecar})")


def _sidecar_checksum(sidecar: Path) -> str | None:
    """``file_sha256`` from a checkpoint's metadata JSON, or None when there is none to read."""
    try:
        meta = json.loads(sidecar.read_text())
    except (OSError, ValueError):
        return None
    value = meta.get(SIDECAR_CHECKSUM_KEY) if isinstance(meta, dict) else None
    return value if isinstance(value, str) else None


def _load_file(p: Path) -> Any:
    """What ``torch.load`` (``weights_only``) finds in ``p``, or an InputError saying why there is nothing."""
    if not p.exists():
        raise InputError(f"{p}: checkpoint not found")
    if p.is_dir():
        raise InputError(f"{p}: is a directory, expected a checkpoint file")
    if not p.is_file():  # reading a FIFO blocks until someone writes to it
        raise InputError(f"{p}: not a regular file (a FIFO, device or socket), expected a checkpoint file")
    if p.stat().st_size == 0:
        raise InputError(f"{p}: empty file, not a checkpoint")
    try:
        with warnings.catch_warnings():
            # torch warns on stderr about pickle protocols it did not write; the error below says it all.
            warnings.simplefilter("ignore")
            return torch.load(p, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        raise InputError(f"{p}: {_refused_pickle_reason(err)}") from None
    except Exception as err:  # any file: torch raises RuntimeError, KeyError, EOFError, ...
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise InputError(f"{p}: not a readable checkpoint (truncated or corrupt?): {first[:200]}") from None


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
    weights = PolicyCheckpoint.read(path).learner
    learner = Learner(LearnerConfig(), seed=0)
    try:
        learner.load_state_dict(weights, load_optimisers=False)
    except (RuntimeError, KeyError) as err:  # shapes or names that do not fit these networks
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise InputError(f"{path}: weights do not fit this build's networks: {first[:200]}") from None
    except InputError as err:
        raise InputError(f"{path}: {err}") from None
    return learner
