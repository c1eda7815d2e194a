"""Writing outputs so that nothing is ever half-written: temp file in the same directory, then rename."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import pandas as pd

from idas_sumo.errors import InputError


@contextlib.contextmanager
def atomic_open(path: Path, mode: str = "w") -> Iterator[IO[Any]]:
    """Open a temp file beside ``path``; it replaces ``path`` only if the block completes."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600; results get the usual permissions
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_csv_atomic(frame: pd.DataFrame, path: Path) -> None:
    with atomic_open(path) as f:
        frame.to_csv(f, index=False, lineterminator="\n")


def prepare_output_dir(out: Path, force: bool, flag: str = "--out") -> Path:
    """Create ``out``; refuse an existing non-empty directory unless ``force``."""
    if out.exists() and not out.is_dir():
        raise InputError(f"{flag} {out}: exists and is not a directory")
    if out.exists() and any(out.iterdir()) and not force:
        raise InputError(
            f"{flag} {out}: directory exists and is not empty (use --force to overwrite its files)"
        )
    return ensure_writable_dir(out, flag)


def ensure_writable_dir(out: Path, flag: str = "--out") -> Path:
    """Create ``out`` (and its parents) if needed; a file in the way or no write permission is an InputError."""
    if out.exists() and not out.is_dir():
        raise InputError(f"{flag} {out}: exists and is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(f"{flag} {out}: cannot create directory ({err.strerror})") from None
    if not os.access(out, os.W_OK):
        raise InputError(f"{flag} {out}: directory is not writable")
    return out
