"""Python in a child process that calls back: the one launcher, key exchange and handshake that the SUMO
child (sim/backend.py) and the worker pools (sim/processes.py) share.

A child is a fresh interpreter started with subprocess, not multiprocessing's spawn: spawn re-imports
the user's ``__main__``, so a script without an ``if __name__ == "__main__":`` guard would run itself
again there. It runs in its own session (process group on Windows), so a Ctrl-C in the terminal
reaches only the parent, which owns its children and stops them.

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
from typing import IO, Any

__all__ = [
    "ACCEPT_SLICE_S",
    "CHILD_HANDSHAKE_TIMEOUT_S",
    "HANDSHAKE_TIMEOUT_S",
    "CallBackServer",
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

    def launch(self, entry: str, stdout: _Stream = None, stderr: _Stream = None) -> subprocess.Popen[bytes]:
        """Start a child that calls back and runs ``entry(conn)`` (``"package.module:function"``);
        ``stdout``/``stderr`` as ``subprocess.Popen`` takes them (None: the parent's)."""
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
                proc.stdin.write(f"{self.port} {self._key.hex()}\n".encode())
                proc.stdin.close()
        except BaseException:
            proc.kill()
            proc.wait()
            raise
        return proc

    def accept(self, procs: Sequence[subprocess.Popen[bytes]], deadline: float) -> Connection:
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
        port, key = sys.stdin.readline().split()
        sys.stdin.close()
        conn = connect(int(port), bytes.fromhex(key))
    except (ValueError, OSError, EOFError, AuthenticationError):
        sys.exit(1)
    module, _, function = entry.partition(":")
    try:
        getattr(importlib.import_module(module), function)(conn)
    except (EOFError, BrokenPipeError, ConnectionResetError):
        sys.exit(1)  # the parent went away mid-task
    except Exception:
        traceback.print_exc()
        sys.exit(1)
