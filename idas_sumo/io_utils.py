"""Writing outputs so that nothing is ever half-written, and nothing a user owns is replaced or removed.

Every temporary file the package makes comes from here and ends in ``.tmp`` (which ``.gitignore``
covers), with the permissions of an ordinary new file. The output-path policy lives here too: a
folder a command writes into is locked while it writes (``LOCK_NAME``), every file the tool writes
there is recorded in its manifest (``MANIFEST_NAME``), ``--force`` removes only what the manifest
lists, and nothing is ever written inside the installed package.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import itertools
import os
import re
import tempfile
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

from idas_sumo.errors import InputError

if TYPE_CHECKING:  # pandas only for the annotation: nets and checkpoints are written without it
    import pandas as pd

TEMP_SUFFIX = ".tmp"
_TEMP_NAME = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp$")
"""What ``_temp_beside`` names a temp file (``mkstemp``'s 8 random characters); other dotfiles are the user's."""
PACKAGE_DIR = Path(__file__).resolve().parent
"""The installed package: its shipped nets, policies and scenarios are never written over."""
MANIFEST_NAME = ".idas-sumo-outputs"
"""In an output folder: the files the tool wrote there, one relative path a line (what ``--force`` removes)."""
LOCK_NAME = ".idas-sumo.lock"
"""In an output folder while a command writes into it: two commands never write into one folder at once."""
_TOOL_FILES = frozenset({MANIFEST_NAME, LOCK_NAME})


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
        record_output(path)
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
        record_output(path)
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
    Only names ``_temp_beside`` makes are touched (``.notes.tmp`` is the user's).
    """
    removed = []
    now = time.time()
    for path in directory.glob(f".*{TEMP_SUFFIX}"):
        if not _TEMP_NAME.match(path.name):
            continue
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


def refuse_package_path(path: Path, flag: str = "--out") -> None:
    """Refuse an output inside the installed package (its shipped net, policies, scenarios)."""
    resolved = path.resolve()
    if resolved == PACKAGE_DIR or PACKAGE_DIR in resolved.parents:
        raise InputError(
            f"{flag} {path}: inside the installed idas_sumo package ({PACKAGE_DIR}), whose shipped files "
            "are never written over; write it elsewhere"
        )


def claim_output_file(path: Path, force: bool, ours: Any, flag: str = "--out") -> None:
    """Check that a command may write the file ``path``: never inside the package, never over a
    directory, and over an existing file only when ``ours(path)`` says the tool wrote it, or with ``force``."""
    refuse_package_path(path, flag)
    if path.is_dir():
        raise InputError(f"{flag} {path}: exists and is not a file")
    if path.exists() and not force and not ours(path):
        raise InputError(
            f"{flag} {path}: exists and was not written by idas-sumo (use --force to replace it)"
        )


def holds_files(out: Path) -> bool:
    """Whether ``out`` holds anything but the tool's own lock and manifest."""
    return out.is_dir() and any(p.name not in _TOOL_FILES for p in out.iterdir())


def claim_fresh_dir(base: Path, flag: str = "--out") -> Path:
    """Create and return ``base``, or if it exists the first of ``base-2``, ``base-3``, … that does not.

    ``mkdir`` without ``exist_ok`` claims the name, so two runs started together never share one.
    """
    refuse_package_path(base, flag)
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
def output_directory(
    out: Path,
    force: bool,
    fresh: bool = False,
    flag: str = "--out",
    keep: bool = False,
    writes: Iterable[str] = (),
    clear_first: bool = False,
) -> Iterator[Path]:
    """The directory a command writes into, for the duration of the block, locked (``LOCK_NAME``) and
    with every file written into it recorded in its manifest.

    ``fresh``: ``out`` or, when that exists, the first free ``out-2``, ``out-3``, …; otherwise ``out``
    itself: refused when it holds files, unless ``force`` or ``keep`` (a resumed run adds to its files).
    With ``force``, the files the manifest lists that the block did not write again are removed when it
    completes (a failed run keeps the earlier outputs), or before it starts with ``clear_first``; all of
    them are checked first. ``writes``: names the command writes, refused when a symlink leads there.
    Temp files of writes killed before their rename are removed.
    If the block fails or is interrupted, every
    directory made here that is still empty is removed again (a new ``out``, empty folders inside it,
    and the parents made for it): completed files stay, empty folders do not.
    """
    new_parents = [p for p in out.parents if not p.exists()]  # nearest first, as they must go
    new_out: Path | None = None
    try:
        if fresh:
            new_out = claim_fresh_dir(out, flag)
        else:
            refuse_package_path(out, flag)
            if out.exists() and not out.is_dir():
                raise InputError(f"{flag} {out}: exists and is not a directory")
            new_out = None if out.exists() else out
            ensure_writable_dir(out, flag)
        where = new_out or out
        with OutputFolder.open(where, flag) as folder:
            if not fresh and not keep and not force and holds_files(where):
                raise InputError(
                    f"{flag} {out}: directory exists and is not empty (use --force to overwrite its files)"
                )
            earlier = folder.check_removal(writes) if not keep else folder.check_links(writes)
            if clear_first:
                folder.remove(earlier)
            remove_stale_temps(where)
            yield where
            folder.remove([path for path in earlier if path not in folder.written])
    except BaseException:
        if new_out is not None and new_out.is_dir():
            _remove_empty_dirs(new_out)
        for parent in new_parents:
            with contextlib.suppress(OSError):
                parent.rmdir()
        raise


_OPEN_FOLDERS: dict[Path, OutputFolder] = {}
"""The output folders this process writes into now (resolved path -> folder): ``record_output`` looks here."""


def record_output(path: Path) -> None:
    """Record ``path`` in the manifest of the open output folder that holds it (none: nothing to do).
    ``atomic_open``/``atomic_path`` call it before the rename, so no file of the tool's goes unrecorded."""
    if not _OPEN_FOLDERS:
        return
    target = path.parent.resolve() / path.name
    for root, folder in _OPEN_FOLDERS.items():
        if root in target.parents:
            folder.record(target.relative_to(root).as_posix())


class OutputFolder:
    """An output folder while a command writes into it: its lock, and the manifest of what the tool wrote."""

    def __init__(self, root: Path, flag: str) -> None:
        self.root, self.flag = root, flag
        self.manifest = root / MANIFEST_NAME
        self.recorded = self._read()
        self.written: set[Path] = set()
        """The files recorded while the folder is open (what a ``--force`` run wrote again)."""

    @classmethod
    @contextlib.contextmanager
    def open(cls, root: Path, flag: str = "--out") -> Iterator[OutputFolder]:
        """Lock ``root`` for the block (another command already holding it: one InputError line)."""
        fd = _lock(root, flag)
        try:
            folder = cls(root, flag)
            key = root.resolve()
            _OPEN_FOLDERS[key] = folder
            try:
                yield folder
            finally:
                del _OPEN_FOLDERS[key]
        finally:
            (root / LOCK_NAME).unlink(missing_ok=True)  # unlinked while still held: see _lock
            os.close(fd)

    def _read(self) -> set[str]:
        if not os.path.lexists(self.manifest):
            return set()
        if self.manifest.is_symlink() or not self.manifest.is_file():
            raise InputError(f"{self.manifest}: not a file; remove it or choose another {self.flag}")
        try:
            lines = self.manifest.read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as err:
            raise InputError(f"{self.manifest}: cannot read it ({err})") from None
        for n, line in enumerate(lines, 1):
            parts = Path(line).parts
            if not line or Path(line).is_absolute() or ".." in parts or "\0" in line:
                raise InputError(
                    f"{self.manifest}: line {n} is not a path inside {self.root} (not written by idas-sumo); "
                    f"remove it or choose another {self.flag}"
                )
        return set(lines)

    def record(self, relative: str) -> None:
        if relative in _TOOL_FILES:
            return
        self.written.add(self.root / relative)
        if relative in self.recorded:
            return
        self.recorded.add(relative)
        self._write()

    def _write(self) -> None:
        if not self.recorded:
            self.manifest.unlink(missing_ok=True)
            return
        fd, tmp = _temp_beside(self.manifest)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write("".join(f"{name}\n" for name in sorted(self.recorded)))
        os.replace(tmp, self.manifest)

    def check_removal(self, also_check: Iterable[str] = ()) -> list[Path]:
        """The files the manifest lists that are there (what ``--force`` removes), all checked first: a
        recorded path that is now a folder, or that leads through a symlink (as could ``also_check``,
        names the run writes next), is one InputError, and nothing is removed."""
        files = []
        for relative in sorted({*self.recorded, *also_check}):
            path = self.root / relative
            self._refuse_links(relative)
            if relative in self.recorded and os.path.lexists(path):
                if not path.is_file():
                    raise InputError(
                        f"{path}: idas-sumo wrote a file there, now it is not one; nothing was removed "
                        f"(remove it yourself or choose another {self.flag})"
                    )
                files.append(path)
        return files

    def remove(self, files: list[Path]) -> None:
        """Remove ``files`` (from ``check_removal``) and the folders that leaves empty; forget them."""
        for path in files:
            path.unlink(missing_ok=True)
            self.recorded.discard(path.relative_to(self.root).as_posix())
        for folder in sorted({p.parent for p in files}, key=lambda p: len(p.parts), reverse=True):
            while folder != self.root and self.root in folder.parents:
                with contextlib.suppress(OSError):
                    folder.rmdir()
                folder = folder.parent
        if files:
            self._write()

    def check_links(self, names: Iterable[str]) -> list[Path]:
        """Refuse a symlink on the way to any of ``names``; nothing to remove (``[]``)."""
        for name in names:
            self._refuse_links(name)
        return []

    def _refuse_links(self, relative: str) -> None:
        """A symlink on the way to ``relative``: writing or removing there would reach outside the folder."""
        here = self.root
        for part in Path(relative).parts:
            here = here / part
            if here.is_symlink():
                raise InputError(
                    f"{here}: a symlink where idas-sumo writes its own files; nothing was removed "
                    f"(remove it yourself or choose another {self.flag})"
                )


def _lock(root: Path, flag: str) -> int:
    """An exclusive ``flock`` on ``root/LOCK_NAME``; its descriptor. The holder unlinks the file when
    done, so one that opened it before is checked to hold the file that is there now."""
    path = root / LOCK_NAME
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as err:
            raise InputError(f"{flag} {root}: cannot lock the folder ({err.strerror})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            other = f" or choose another {flag}" if flag.startswith("--") else ""
            raise InputError(
                f"{flag} {root}: another idas-sumo command is writing into this folder; "
                f"wait for it to finish{other}"
            ) from None
        try:
            current = os.stat(path, follow_symlinks=False).st_ino
        except FileNotFoundError:
            current = -1
        if current == os.fstat(fd).st_ino:
            return fd
        os.close(fd)


def _remove_empty_dirs(top: Path) -> None:
    """Remove ``top`` and the folders under it that hold no file (never a file)."""
    for here, _, _ in os.walk(top, topdown=False):
        with contextlib.suppress(OSError):
            os.rmdir(here)


def ensure_writable_dir(out: Path, flag: str = "--out") -> Path:
    """Create ``out`` (and its parents) if needed; a file in the way, no write permission or a folder of
    the installed package is an InputError."""
    refuse_package_path(out, flag)
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


def is_matplotlib_png(path: Path) -> bool:
    """A PNG that matplotlib wrote (``save_png``'s files: their ``Software`` text chunk names it)."""
    try:
        with path.open("rb") as f:
            head = f.read(256)
    except OSError:
        return False
    return head.startswith(b"\x89PNG") and b"Software\x00Matplotlib" in head


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
