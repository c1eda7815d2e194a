"""Worker processes that call back: what ``train --workers`` and ``evaluate --workers`` share.

A worker is a child started by sim/rpc.py (as the SUMO child of sim/backend.py is): a fresh interpreter
in its own session that calls back on an authenticated loopback socket and then runs the entry function
named by the parent with the connection. Start-up stays interruptible: the parent waits for call-backs
in short slices, so Ctrl-C or SIGTERM is seen within a fraction of a second; on any failure or
interruption every started worker is killed at once (not waited for), and a worker whose parent is gone
before it connected exits without a traceback. Within ``worker_fork_server`` (``idas-sumo train`` with two
or more workers), a pool's workers are forks of one such child that imported their module once
(``rpc.ForkServer``), instead of fresh interpreters that each import it again.

What the workers do is a ``Server`` (built from a start-up value, then asked requests); ``WorkerPool``
is what training and evaluation see of them, implemented here by ``ProcessPool`` (these processes)
and by ``distributed/ray_pool.py``'s ``RayPool`` (Ray actors), so both backends run the same code.
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import os
import subprocess
import tempfile
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from multiprocessing.connection import Connection
from types import TracebackType
from typing import IO, Any, Protocol

from idas_sumo.errors import InputError, SimulationError
from idas_sumo.sim.rpc import CallBackServer, Child, ForkServer, NoCallBack

log = logging.getLogger(__name__)

__all__ = [
    "SEED_LIMIT",
    "ProcessPool",
    "Server",
    "WorkerPool",
    "WorkerProcesses",
    "derived_seed",
    "max_workers",
    "release_fork_server",
    "serve",
    "wait_any",
    "worker_fork_server",
]

SEED_LIMIT = 2**31
"""Seeds lie in [0, SEED_LIMIT): SUMO's ``--seed`` is a C int. ``--seed`` is checked against it once,
in the CLI; seeds derived from it (one per worker) wrap around with ``derived_seed``."""
CONNECT_TIMEOUT_S = 120.0
"""How long a starting worker may take to import torch and call back before the run gives up."""
CLOSE_TIMEOUT_S = 10.0
"""How long a worker asked to stop may take to close its SUMO before it is killed."""
KILL_GRACE_S = 3.0
"""How long a worker told to stop at once (SIGTERM) may take to clean up before it is killed."""
_POLL_S = 0.2
POOL_ENTRY = "idas_sumo.sim.processes:serve"
"""What a ``ProcessPool`` worker runs."""


def max_workers() -> int:
    """The most worker processes a run may start: the CPUs this process may use. Each runs its own SUMO
    at full speed, so more would only share the same cores (and memory) and slow every one down."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def derived_seed(seed: int, offset: int) -> int:
    """``seed + offset`` inside SUMO's seed range (a worker's seed next to the run's own)."""
    return (seed + offset) % SEED_LIMIT


class WorkerProcesses:
    """``count`` workers, each running ``entry(conn)`` (``"package.module:function"``) on its own
    connection; ``conns[i]`` talks to worker i. ``what`` names them in messages ("rollout worker").

    ``capture_stderr``: each worker's stderr goes to an anonymous temporary file (gone with the
    process, even after SIGKILL) whose last lines ``stderr_tail`` returns; otherwise the workers
    share the parent's stderr.
    """

    def __init__(self, entry: str, count: int, what: str, capture_stderr: bool = False) -> None:
        limit = max_workers()
        if not 1 <= count <= limit:
            raise InputError(f"workers: {count} is not in [1, {limit}] (this machine's CPUs)")
        self.what = what
        self.conns: list[Connection] = []
        self.procs: list[Child] = []
        self._stderr: list[IO[bytes]] = []
        try:
            with CallBackServer() as server:
                deadline = time.monotonic() + CONNECT_TIMEOUT_S
                if not capture_stderr:  # (a fork writes to the fork server's stderr: the parent's)
                    self.procs = _forked(server, entry, count, deadline)
                for _ in range(count - len(self.procs)):
                    # Anonymous (no name to leak), closed in kill() with its worker.
                    err: IO[bytes] | None = tempfile.TemporaryFile() if capture_stderr else None  # noqa: SIM115
                    if err is not None:
                        self._stderr.append(err)
                    # stdout goes nowhere: libsumo prints there.
                    self.procs.append(server.launch(entry, stdout=subprocess.DEVNULL, stderr=err))
                while len(self.conns) < count:
                    self.conns.append(self._accept(server, deadline))
        except BaseException:
            self.kill()
            raise

    def _accept(self, server: CallBackServer, deadline: float) -> Connection:
        """The next worker's authenticated connection (``CallBackServer.accept``); an error if every
        worker died or none called back in time."""
        try:
            return server.accept(self.procs, deadline)
        except NoCallBack as err:
            if err.exited:
                raise SimulationError(self._failed_to_start()) from None
            raise SimulationError(f"{self._a} did not start within {CONNECT_TIMEOUT_S:g} s") from None

    def _failed_to_start(self) -> str:
        tail = self.stderr_tail(0) if self._stderr else ""
        where = f": {tail}" if tail else " (see its error above)"
        return f"{self._a} failed to start{where}"

    @property
    def _a(self) -> str:
        return f"{'an' if self.what[:1] in 'aeiou' else 'a'} {self.what}"

    def stderr_tail(self, i: int, lines: int = 5) -> str:
        """The last ``lines`` lines of worker i's captured stderr, joined with " | " ("" if none)."""
        if i >= len(self._stderr):
            return ""
        f = self._stderr[i]
        f.flush()
        f.seek(0)
        text = f.read().decode(errors="replace").strip()
        return " | ".join(text.splitlines()[-lines:])

    def close(self, message: Any = None) -> None:
        """Stop the workers: send ``message`` (the entry's "stop" request) if given, give each
        ``CLOSE_TIMEOUT_S`` to exit (closing its SUMO), then kill what is left."""
        if message is not None:
            for conn in self.conns:
                with contextlib.suppress(OSError):
                    conn.send(message)
        deadline = time.monotonic() + CLOSE_TIMEOUT_S
        for proc in self.procs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=max(deadline - time.monotonic(), 0.0))
        self.kill()

    def kill(self) -> None:
        """Stop every worker now (an error or an interruption: nothing to wait for). SIGTERM first,
        which a worker turns into an exit through its cleanup (its SUMO's temporary folder goes
        too), then SIGKILL for any still there after ``KILL_GRACE_S``."""
        for proc in self.procs:
            if proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.terminate()
        deadline = time.monotonic() + KILL_GRACE_S
        try:
            for proc in self.procs:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(timeout=max(deadline - time.monotonic(), 0.0))
        finally:  # also when a second Ctrl-C cuts the grace period short: no worker survives us
            for proc in self.procs:
                if proc.poll() is None:
                    with contextlib.suppress(ProcessLookupError):
                        proc.kill()
                    proc.wait()
        for conn in self.conns:
            conn.close()
        for f in self._stderr:
            f.close()
        self.conns, self.procs, self._stderr = [], [], []


_fork_servers: list[ForkServer] = []
"""The fork server of ``worker_fork_server``'s block, while it runs."""


@contextlib.contextmanager
def worker_fork_server(preload: str) -> Iterator[None]:
    """Within the block, ``ProcessPool`` workers (those sharing the parent's stderr) are forked from one child
    started now that imports ``preload`` (the module of the servers they will run; ``"module:function"`` also
    calls that function, e.g. to load what each worker would) beside this process's own imports: each worker
    starts with it imported, instead of importing it again. Nothing where ``os.fork`` is
    not (``ForkServer.available``)."""
    if not ForkServer.available:
        yield
        return
    server = ForkServer(preload)
    _fork_servers.append(server)
    try:
        yield
    finally:
        release_fork_server()


def release_fork_server() -> None:
    """Stop the fork server now (a run that turned out to need no worker processes): it holds its imports'
    memory."""
    while _fork_servers:
        _fork_servers.pop().close(CLOSE_TIMEOUT_S)


def _forked(server: CallBackServer, entry: str, count: int, deadline: float) -> list[Child]:
    """``count`` children forked from the fork server to call back on ``server``, or none if there is none or it
    failed (the caller starts its own children then)."""
    if not _fork_servers:
        return []
    forked: list[Child] = []
    try:
        for _ in range(count):
            forked.append(_fork_servers[-1].fork(server, entry, deadline))
    except (NoCallBack, EOFError, OSError):
        log.warning("the workers' fork server did not start; starting each worker on its own")
        release_fork_server()
        for child in forked:
            child.kill()
        return []
    return forked


def wait_any(conns: Sequence[Connection], timeout_s: float = _POLL_S) -> list[Connection]:
    """The connections among ``conns`` with a message (or an EOF) waiting, after at most
    ``timeout_s``: a short slice, so that the caller's loop sees a signal at once."""
    from multiprocessing.connection import wait

    return [c for c in wait(list(conns), timeout=timeout_s) if isinstance(c, Connection)]


# --- the worker pool: what training and evaluation ask of their workers, whichever backend runs them ----


class Server(Protocol):
    """What a worker runs: built once from its start-up value, then asked requests until closed.

    ``handle`` returns its reply (errors included, as values: an exception raised here means the
    worker itself is broken). ``shared`` is the part of a request that every worker of a round gets
    (the actor weights): a backend may send it once for all of them. A server may also have
    ``work_ahead()``: called once each reply is on its way, before the next request is read (``run_ahead``).
    """

    def handle(self, request: Any, shared: Any) -> Any: ...

    def close(self) -> None: ...


ServerFactory = Callable[[Any], Server]

_CLOSE = ("close",)
"""A process worker's last message: close the server and exit."""


def run_ahead(server: Server) -> None:
    """The server's ``work_ahead``, if it has one (what its next request may use: it must not change a reply)."""
    work_ahead = getattr(server, "work_ahead", None)
    if work_ahead is not None:
        work_ahead()


def load_factory(factory: str) -> ServerFactory:
    """``"package.module:name"``: the callable that builds a worker's ``Server`` from its start-up value."""
    module, _, name = factory.partition(":")
    built: ServerFactory = getattr(importlib.import_module(module), name)
    return built


class WorkerPool(ABC):
    """Workers 0..size-1, each holding the ``Server`` that ``factory`` built from its start-up value.

    Two backends implement it: ``ProcessPool`` (processes on this machine) and
    ``idas_sumo.distributed.ray_pool.RayPool`` (Ray actors, on a cluster). Training and evaluation
    only see this interface, so the episodes and their order are the same on both.
    """

    what: str
    """What the workers are, for messages ("rollout worker")."""

    @property
    @abstractmethod
    def size(self) -> int: ...

    @abstractmethod
    def submit(self, requests: Mapping[int, Any], shared: Any = None) -> None:
        """Ask worker i ``requests[i]`` (with ``shared``), without waiting for the replies."""

    @abstractmethod
    def finished(self, pending: Collection[int], timeout_s: float = _POLL_S) -> list[int]:
        """The workers among ``pending`` whose reply is in, after at most ``timeout_s`` (a short
        slice, so the caller sees a signal at once)."""

    @abstractmethod
    def result(self, i: int) -> Any:
        """Worker i's reply to its last request (waits for it); a ``SimulationError`` if it died."""

    @abstractmethod
    def close(self) -> None:
        """Close every server (its SUMO) and stop the workers."""

    @abstractmethod
    def kill(self) -> None:
        """Stop every worker now (after an error or an interruption)."""

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        # After an error or an interruption the workers may be mid-request: stop them now, not after it.
        if exc_type is None:
            self.close()
        else:
            self.kill()


class _Beside:
    """``task`` on a thread of its own from now on, if any; ``join`` waits for it and raises its error."""

    def __init__(self, task: Callable[[], None] | None) -> None:
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None
        if task is not None:
            self._thread = threading.Thread(target=self._run, args=(task,), daemon=True)
            self._thread.start()

    def _run(self, task: Callable[[], None]) -> None:
        try:
            task()
        except BaseException as err:  # (raised again in the caller's thread by ``join``)
            self._error = err

    def join(self) -> None:
        """Wait for the task (at once after the first time), then raise its error (only the first time)."""
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        error, self._error = self._error, None
        if error is not None:
            raise error


class ProcessPool(WorkerPool):
    """One ``WorkerProcesses`` worker per start-up value, each running ``serve``."""

    def __init__(
        self,
        factory: str,
        inits: Sequence[Any],
        what: str,
        capture_stderr: bool = False,
        meanwhile: Callable[[], None] | None = None,
    ) -> None:
        """``meanwhile``: work of the caller's own, run on a thread of its while the workers start and their first
        requests go out (the caller would wait for them), finished before the first ``submit`` (or ``close``)
        returns; its error is raised there."""
        self.what = what
        self._beside = _Beside(meanwhile)
        self._procs = WorkerProcesses(POOL_ENTRY, len(inits), what, capture_stderr)
        try:
            for conn, init in zip(self._procs.conns, inits, strict=True):
                conn.send((factory, init))
        except BaseException:
            self._procs.kill()
            raise

    @property
    def size(self) -> int:
        return len(self._procs.conns)

    def submit(self, requests: Mapping[int, Any], shared: Any = None) -> None:
        for i, request in requests.items():
            try:
                self._procs.conns[i].send((request, shared))
            except (BrokenPipeError, EOFError, OSError):
                raise SimulationError(self._died(i)) from None
        self._beside.join()

    def finished(self, pending: Collection[int], timeout_s: float = _POLL_S) -> list[int]:
        conns = self._procs.conns
        ready = {id(c) for c in wait_any([conns[i] for i in pending], timeout_s)}
        return [i for i in pending if id(conns[i]) in ready]

    def result(self, i: int) -> Any:
        try:
            return self._procs.conns[i].recv()
        except (EOFError, OSError):
            raise SimulationError(self._died(i)) from None

    def _died(self, i: int) -> str:
        proc = self._procs.procs[i]
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=KILL_GRACE_S)
        tail = self._procs.stderr_tail(i)
        code = "" if proc.returncode is None else f" with code {proc.returncode}"
        return f"{self.what} {i} exited{code} without results" + (f": {tail}" if tail else "")

    def close(self) -> None:
        self._procs.close(_CLOSE)
        self._beside.join()

    def kill(self) -> None:
        self._procs.kill()


def serve(conn: Connection) -> None:
    """A ``ProcessPool`` worker (the ``WorkerProcesses`` entry): build the server from the first
    message, then answer (request, shared) messages until ``_CLOSE``; the server is closed (its SUMO
    and temporary folder go) however this ends."""
    factory, init = conn.recv()
    server = load_factory(factory)(init)
    try:
        while True:
            message = conn.recv()
            if message == _CLOSE:
                break
            request, shared = message
            conn.send(server.handle(request, shared))
            run_ahead(server)
    except (EOFError, BrokenPipeError):
        pass  # the parent went away: nothing to answer
    finally:
        server.close()
