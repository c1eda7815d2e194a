"""Writing outputs so that nothing is ever half-written: temp file in the same directory, then rename.

Every temporary file the package makes comes from here and ends in ``.tmp`` (which ``.gitignore``
covers), with the permissions of an ordinary new file.
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

from idas_sumo.errors import InputError

if TYPE_CHECKING:  # pandas only for the annotation: nets and checkpoints are written without it
    import pandas as pd

TEMP_SUFFIX = ".tmp"


def _temp_beside(path: Path) -> tuple[int, Path]:
    """A new, empty ``.<name>.XXXX.tmp`` beside ``path``: its open descriptor and its path."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=TEMP_SUFFIX)
    os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600; outputs get the usual permissions
    return fd, Path(tmp)


@contextlib.contextmanager
def atomic_open(path: Path, mode: str = "w", **open_kwargs: Any) -> Iterator[IO[Any]]:
    """Open a temp file beside ``path``; it replaces ``path`` only if the block completes.

    ``open_kwargs`` (``newline``, ``encoding``) go to ``open``.
    """
    fd, tmp = _temp_beside(path)
    try:
        with os.fdopen(fd, mode, **open_kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(err, OSError) and err.filename is None and err.errno is not None:
            # A failed write names no file ("No space left on device"): name the one being written.
            raise OSError(err.errno, err.strerror, str(path)) from None
        raise


@contextlib.contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """A temp file's path beside ``path``, for a tool that writes by file name (netconvert); it replaces
    ``path`` only if the block completes, and is removed otherwise."""
    fd, tmp = _temp_beside(path)
    os.close(fd)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def remove_stale_temps(directory: Path, older_than_s: float = 0.0) -> list[Path]:
    """Remove the temp files ``atomic_open``/``atomic_path`` left in ``directory`` when a write was
    killed before its rename (SIGKILL, power loss: no cleanup ran); the files removed.

    Call it when a run starts in ``directory``: a temp file there is then never a live write (two
    runs never write into one directory at once). In a directory that several processes write at
    once (the net cache), ``older_than_s`` spares the temp files of writes that may still be live.
    """
    removed = []
    now = time.time()
    for path in directory.glob(f".*{TEMP_SUFFIX}"):
        with contextlib.suppress(OSError):
            if older_than_s and now - path.lstat().st_mtime < older_than_s:
                continue
        if path.is_file() and not path.is_symlink():
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
                removed.append(path)
    return removed


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_csv_atomic(frame: pd.DataFrame, path: Path) -> None:
    """``frame`` as CSV; a missing value (NaN) is an empty cell."""
    with atomic_open(path) as f:
        frame.to_csv(f, index=False, lineterminator="\n", na_rep="")


def prepare_output_dir(out: Path, force: bool, flag: str = "--out") -> Path:
    """Create ``out``; refuse an existing non-empty directory unless ``force``."""
    if out.exists() and not out.is_dir():
        raise InputError(f"{flag} {out}: exists and is not a directory")
    if out.exists() and any(out.iterdir()) and not force:
        raise InputError(
            f"{flag} {out}: directory exists and is not empty (use --force to overwrite its files)"
        )
    return ensure_writable_dir(out, flag)


def claim_fresh_dir(base: Path, flag: str = "--out") -> Path:
    """Create and return ``base``, or if it exists the first of ``base-2``, ``base-3``, … that does not.

    ``mkdir`` without ``exist_ok`` claims the name, so two runs started together never share one.
    """
    ensure_writable_dir(base.parent, flag)
    for n in itertools.count(1):
        candidate = base if n == 1 else base.with_name(f"{base.name}-{n}")
        try:
            candidate.mkdir()
        except FileExistsError:
            continue
        except OSError as err:
            raise InputError(f"{flag} {candidate}: cannot create directory ({err.strerror})") from None
        return candidate
    raise AssertionError("unreachable")  # pragma: no cover


@contextlib.contextmanager
def output_directory(out: Path, force: bool, fresh: bool = False, flag: str = "--out") -> Iterator[Path]:
    """The directory a command writes into, for the duration of the block.

    ``fresh``: ``out`` or, when that exists, the first free ``out-2``, ``out-3``, …; otherwise ``out``
    itself (``prepare_output_dir``: refused when it holds files, unless ``force``). If the block fails
    or is interrupted, every directory made here that is still empty is removed again (a new ``out``,
    empty folders inside it, and the parents made for it): completed files stay, empty folders do not.
    """
    new_parents = [p for p in out.parents if not p.exists()]  # nearest first, as they must go
    new_out: Path | None = None
    try:
        if fresh:
            new_out = claim_fresh_dir(out, flag)
            yield new_out
        else:
            if not out.exists():
                new_out = out
            yield prepare_output_dir(out, force, flag)
    except BaseException:
        if new_out is not None and new_out.is_dir():
            _remove_empty_dirs(new_out)
        for parent in new_parents:
            with contextlib.suppress(OSError):
                parent.rmdir()
        raise


def _remove_empty_dirs(top: Path) -> None:
    """Remove ``top`` and the folders under it that hold no file (never a file)."""
    for here, _, _ in os.walk(top, topdown=False):
        with contextlib.suppress(OSError):
            os.rmdir(here)


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


def file_digest(path: Path) -> str:
    """The SHA-256 (hex) of a file's bytes, as ``sha256sum`` prints it."""
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def save_png(fig: Any, path: Path, dpi: int = 120) -> Path:
    """A matplotlib figure as a PNG, written atomically, then closed (every plot of the package)."""
    import matplotlib.pyplot as plt

    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return path


def read_csv_columns(path: Path, columns: tuple[str, ...], written_by: str) -> Any:
    """A CSV as a pandas DataFrame that has ``columns``; anything else is one InputError naming the file and
    the command that writes such files (``written_by``, e.g. "idas-sumo train")."""
    import pandas as pd

    try:
        frame = pd.read_csv(path)
    except (OSError, pd.errors.ParserError, pd.errors.EmptyDataError) as err:
        raise InputError(f"{path}: cannot read CSV ({err})") from None
    missing = [c for c in columns if c not in frame.columns]
    if missing:
        raise InputError(f"{path}: not written by `{written_by}` (missing columns: {', '.join(missing)})")
    return frame
