"""Python in a child process that calls back: the one launcher, key exchange and handshake that the SUMO
child (sim/backend.py) and the worker pools (sim/processes.py) share.

A child is a fresh interpreter started with subprocess, not multiprocessing's spawn: spawn re-imports
the user's ``__main__``, so a script without an ``if __name__ == "__main__":`` guard would run itself
again there. It runs in its own session (process group on Windows), so a Ctrl-C in the terminal
reaches only the parent, which owns its children and stops them. A ``ForkServer`` is such a child
that imports the modules its forks need once, beside the parent's own imports, and then forks a child
for each one asked (Linux): the fork takes its own session and calls back as a launched child does.
It forks from a process that has imported but computed nothing (no torch or OpenMP thread pool
started), not from the parent, and never imports the parent's ``__main__``.

The parent listens on a loopback port and hands each child the port and a fresh random key on its
stdin (not its command line, where other users could read it). The child connects, and each side
proves it holds the key (multiprocessing's HMAC challenge, both ways) before anything is unpickled:
the handshake reads raw bytes only, and only then does the socket become a ``Connection``, over which
messages travel pickled in length-prefixed frames (not over the child's stdout, where libsumo prints).
Every read of the handshake has a deadline: a local program that connects and says nothing is dropped
after ``HANDSHAKE_TIMEOUT_S`` and the wait for the real child goes on.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import secrets
import signal
import socket
import struct
import subprocess
import sys
import time
import traceback
import typing
from collections.abc import Sequence
from multiprocessing import AuthenticationError
from multiprocessing.connection import Connection, answer_challenge, deliver_challenge
from pathlib import Path
from types import TracebackType
from typing import IO, Any, NoReturn, Protocol

__all__ = [
    "ACCEPT_SLICE_S",
    "CHILD_HANDSHAKE_TIMEOUT_S",
    "HANDSHAKE_TIMEOUT_S",
    "CallBackServer",
    "Child",
    "ForkServer",
    "ForkedChild",
    "NoCallBack",
    "child_main",
    "connect",
]

HANDSHAKE_TIMEOUT_S = 5.0
"""How long the parent gives a caller to complete the handshake before it drops the caller."""
CHILD_HANDSHAKE_TIMEOUT_S = 300.0
"""How long a child waits on its parent's side of the handshake. Longer than any parent waits for its
children (it may be dropping silent callers first): the parent, which kills its children, gives up first."""
ACCEPT_SLICE_S = 0.2
"""The parent waits for call-backs in slices this long, so a Ctrl-C or SIGTERM is handled at once."""
_KEY_BYTES = 32
_CHILD_CODE = (
    "import sys; sys.path.append(sys.argv[1]); "
    "from idas_sumo.sim.rpc import child_main; child_main(sys.argv[2])"
)
_PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])
"""The directory holding this idas_sumo, for a parent that found it through its own sys.path edits."""

_Stream = int | IO[bytes] | None


class NoCallBack(Exception):
    """No child called back: every one has exited (``exited``), or the deadline passed."""

    def __init__(self, exited: bool) -> None:
        super().__init__("every child exited" if exited else "no child called back in time")
        self.exited = exited


class CallBackServer:
    """A loopback port and a fresh key: ``launch`` starts children that call back on it, ``accept``
    returns the next one's authenticated connection. Closed on leaving its ``with`` block."""

    def __init__(self) -> None:
        self._key = secrets.token_bytes(_KEY_BYTES)
        self._server = socket.create_server(("127.0.0.1", 0))
        self._server.settimeout(ACCEPT_SLICE_S)
        self.port: int = self._server.getsockname()[1]

    def __enter__(self) -> CallBackServer:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        self._server.close()

    def ticket(self) -> tuple[int, str]:
        """The port and the key (hex) a child needs to call back: what a ``ForkServer`` hands its forks."""
        return self.port, self._key.hex()

    def launch(
        self, entry: str, stdout: _Stream = None, stderr: _Stream = None, preload: str = ""
    ) -> subprocess.Popen[bytes]:
        """Start a child that calls back and runs ``entry(conn)`` (``"package.module:function"``);
        ``stdout``/``stderr`` as ``subprocess.Popen`` takes them (None: the parent's). ``preload``: a module
        the child imports before it calls back (what its entry will need), so that it imports while the
        parent is still busy; ``"module:function"`` also calls that function of it then."""
        group: dict[str, Any] = {"start_new_session": True}
        if sys.platform == "win32":
            group = {"creationflags": subprocess.CREATE_NEW_PROCESS_GROUP}
        # -P: the user's working directory must not shadow modules in the child.
        proc = subprocess.Popen(
            [sys.executable, "-P", "-c", _CHILD_CODE, _PACKAGE_ROOT, entry],
            stdin=subprocess.PIPE,
            stdout=stdout,
            stderr=stderr,
            **group,
        )
        try:
            assert proc.stdin is not None
            with contextlib.suppress(OSError):  # a child that died at once is seen to exit in accept()
                proc.stdin.write(f"{self.port} {self._key.hex()} {preload}\n".encode())
                proc.stdin.close()
        except BaseException:
            proc.kill()
            proc.wait()
            raise
        return proc

    def accept(self, procs: Sequence[Child], deadline: float) -> Connection:
        """The next child's authenticated connection, waited for in short slices. A caller that fails
        the handshake or does not finish it in ``HANDSHAKE_TIMEOUT_S`` (another local program) is
        dropped and the wait goes on. ``NoCallBack`` once every one of ``procs`` has exited, or at
        ``deadline`` (``time.monotonic``)."""
        while True:
            try:
                sock, _ = self._server.accept()
            except TimeoutError:
                if all(p.poll() is not None for p in procs):
                    raise NoCallBack(exited=True) from None
                if time.monotonic() > deadline:
                    raise NoCallBack(exited=False) from None
                continue
            with contextlib.suppress(AuthenticationError, EOFError, OSError):
                return authenticated(sock, self._key, challenge_first=True, timeout_s=HANDSHAKE_TIMEOUT_S)


def connect(port: int, key: bytes) -> Connection:
    """A child's side: call back on the parent's loopback ``port`` and answer its challenge."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=CHILD_HANDSHAKE_TIMEOUT_S)
    return authenticated(sock, key, challenge_first=False, timeout_s=CHILD_HANDSHAKE_TIMEOUT_S)


def authenticated(sock: socket.socket, key: bytes, challenge_first: bool, timeout_s: float) -> Connection:
    """``sock`` as a ``Connection`` once each side proved it holds ``key`` (the one that accepted
    challenges first); the whole handshake may take ``timeout_s``. ``sock`` is closed on any failure."""
    try:
        frames = typing.cast(Connection, _Frames(sock, time.monotonic() + timeout_s))
        if challenge_first:
            deliver_challenge(frames, key)
            answer_challenge(frames, key)
        else:
            answer_challenge(frames, key)
            deliver_challenge(frames, key)
        sock.settimeout(None)
    except BaseException:
        sock.close()
        raise
    return Connection(sock.detach())


class _Frames:
    """multiprocessing's framing (a 4-byte big-endian length, then the bytes) on a socket, each read
    bounded by ``deadline``: what the challenge functions need of a ``Connection``, for the handshake.
    Raw bytes only, never unpickled."""

    def __init__(self, sock: socket.socket, deadline: float) -> None:
        self._sock = sock
        self._deadline = deadline

    def send_bytes(self, buf: bytes) -> None:
        self._sock.settimeout(self._left())
        self._sock.sendall(struct.pack("!i", len(buf)) + buf)

    def recv_bytes(self, maxlength: int) -> bytes:
        (size,) = struct.unpack("!i", self._exactly(4))
        if not 0 <= size <= maxlength:
            raise OSError("bad message length")  # what Connection.recv_bytes raises
        return self._exactly(size)

    def _exactly(self, n: int) -> bytes:
        data = bytearray()
        while len(data) < n:
            self._sock.settimeout(self._left())
            chunk = self._sock.recv(n - len(data))
            if not chunk:
                raise EOFError
            data += chunk
        return bytes(data)

    def _left(self) -> float:
        left = self._deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("the handshake took too long")
        return left


class Child(Protocol):
    """What a parent needs of a child it started: a ``subprocess.Popen``, or a ``ForkedChild``."""

    pid: int
    returncode: int | None

    def poll(self) -> int | None: ...

    def wait(self, timeout: float | None = None) -> int: ...

    def terminate(self) -> None: ...

    def kill(self) -> None: ...


class ForkedChild:
    """A child forked by a ``ForkServer``: the fork server's child, not ours, so its exit status is the fork
    server's to collect (at once); ``returncode`` is that of a signal we sent it, or 1 once it is gone otherwise."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.returncode: int | None = None
        self._signal = 0

    def poll(self) -> int | None:
        if self.returncode is None:
            try:
                os.kill(self.pid, 0)  # (the fork server collects its forks at once: a gone one is no zombie)
            except (ProcessLookupError, PermissionError):  # (gone; its pid another user's since)
                self.returncode = -self._signal if self._signal else 1
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while (code := self.poll()) is None:
            if deadline is not None and time.monotonic() > deadline:
                raise subprocess.TimeoutExpired(f"pid {self.pid}", timeout or 0.0)
            time.sleep(0.02)
        return code

    def _send(self, signum: int) -> None:
        if self.poll() is None:
            self._signal = signum
            with contextlib.suppress(ProcessLookupError):  # (it exited just now)
                os.kill(self.pid, signum)

    def terminate(self) -> None:
        self._send(signal.SIGTERM)

    def kill(self) -> None:
        self._send(signal.SIGKILL)


FORK_SERVER_ENTRY = "idas_sumo.sim.rpc:serve_forks"


class ForkServer:
    """A child that imports ``preload`` once and then forks children that call back, each of which starts with
    those modules imported instead of importing them again (Linux only: ``available``). It calls back on its own
    server once its imports are done; ``fork`` waits for that."""

    available = sys.platform.startswith("linux")

    def __init__(self, preload: str) -> None:
        self._server = CallBackServer()
        self._conn: Connection | None = None
        try:
            # stdout goes nowhere (libsumo prints there); stderr is the parent's, and so its forks'.
            self._proc = self._server.launch(FORK_SERVER_ENTRY, stdout=subprocess.DEVNULL, preload=preload)
        except BaseException:
            self._server.close()
            raise

    def fork(self, server: CallBackServer, entry: str, deadline: float) -> ForkedChild:
        """A forked child that calls back on ``server`` and runs ``entry(conn)``; ``NoCallBack`` if the fork
        server did not start (its imports failed) by ``deadline``, ``EOFError`` or ``OSError`` if it is gone."""
        if self._conn is None:
            self._conn = self._server.accept([self._proc], deadline)
            self._server.close()
        self._conn.send((*server.ticket(), entry))
        return ForkedChild(int(self._conn.recv()))

    def close(self, timeout_s: float) -> None:
        """Stop the fork server once its forks have exited (their parent stops them), at most ``timeout_s`` later:
        it collects their exit, so their CPU time counts among this process's children's."""
        self._server.close()
        if self._conn is None:  # never called back: it has no forks
            self._proc.kill()
        else:
            self._conn.close()
        try:
            self._proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()


def serve_forks(conn: Connection) -> None:
    """A ``ForkServer`` (its child's entry): fork a child for every (port, key, entry) asked, answer its pid; when
    the parent hangs up, wait for the forks to exit, then exit."""
    signal.signal(signal.SIGCHLD, _reap_forks)  # (a fork that exits is no zombie: its parent sees it gone)
    try:
        while True:
            try:
                port, key, entry = conn.recv()
            except (EOFError, OSError):
                break
            pid = os.fork()
            if pid == 0:
                signal.signal(signal.SIGCHLD, signal.SIG_DFL)
                conn.close()
                _forked_child(int(port), bytes.fromhex(key), entry)
            conn.send(pid)
    finally:
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        with contextlib.suppress(ChildProcessError):
            while True:  # each exit collected: the forks' CPU time adds to this process's children's
                os.wait()


def _reap_forks(signum: int, frame: object) -> None:
    """SIGCHLD in the fork server: collect every fork that has exited."""
    with contextlib.suppress(ChildProcessError):
        while os.waitpid(-1, os.WNOHANG)[0]:
            pass


def _forked_child(port: int, key: bytes, entry: str) -> NoReturn:
    """A fork of the fork server: its own session (Ctrl-C in the terminal is the parent's), call back, run
    ``entry(conn)``, exit (never back into the fork server's loop)."""
    code = 1
    try:
        os.setsid()
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        module, _, function = entry.partition(":")
        conn = connect(port, key)
        getattr(importlib.import_module(module), function)(conn)
        code = 0
    except SystemExit as stop:  # SIGTERM from the parent (``_exit_on_sigterm``), after the finally blocks
        code = stop.code if isinstance(stop.code, int) else 1
    except (EOFError, BrokenPipeError, ConnectionResetError, OSError, AuthenticationError):
        code = 1  # the parent went away
    except BaseException:
        traceback.print_exc()
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)


def _exit_on_sigterm(signum: int, frame: object) -> None:
    """SIGTERM from the parent: exit through the finally blocks, so SUMO is closed and its temporary
    folder removed, quietly (SystemExit prints no traceback)."""
    sys.exit(128 + signum)


def child_main(entry: str) -> None:
    """A child (``_CHILD_CODE``): read the port and key on stdin, call back, run ``entry(conn)``. A
    parent that is gone (it failed, was interrupted, or killed us while we started) is not worth a
    traceback."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent owns Ctrl-C and stops us
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
    try:
        port, key, *preload = sys.stdin.readline().split()
        sys.stdin.close()
    except (ValueError, OSError):
        sys.exit(1)
    module, _, function = entry.partition(":")
    try:
        for name in preload:  # a module, or "module:function" to call once it is imported
            preloaded, _, prepare = name.partition(":")
            imported = importlib.import_module(preloaded)
            if prepare:
                getattr(imported, prepare)()
        try:
            conn = connect(int(port), bytes.fromhex(key))
        except (ValueError, OSError, EOFError, AuthenticationError):
            sys.exit(1)
        getattr(importlib.import_module(module), function)(conn)
    except (EOFError, BrokenPipeError, ConnectionResetError):
        sys.exit(1)  # the parent went away mid-task
    except Exception:
        traceback.print_exc()
        sys.exit(1)
