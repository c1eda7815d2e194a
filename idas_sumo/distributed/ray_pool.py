"""The Ray backend: a ``WorkerPool`` of Ray actors, and whole runs as Ray tasks (``sweep``).

Only imported when a command has ``--ray-address``: it imports ``ray`` (the optional extra). The
learner (or the evaluation's bookkeeping) stays in the command's process, the "driver"; each worker
is an actor holding the same ``Server`` a ``ProcessPool`` process holds (a ``RolloutServer`` or an
``EvalServer``), so the episodes, and the CSVs and weights made from them, are the same as with
local workers. A round's actor weights go into the object store once (``ray.put``) and every actor
reads them from there; the packed episodes come back through it too.

Every node must have idas-sumo (the same version) installed, and the paths a run names (the net, a
policy, the output folders) must be the same on every node: a shared file system, or copies.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from typing import Any, TypeVar

from idas_sumo.distributed import LOCAL, check_ray_address, require_ray
from idas_sumo.errors import IdasError, InputError, SimulationError
from idas_sumo.sim.processes import CLOSE_TIMEOUT_S, WorkerPool, load_factory, run_ahead

__all__ = ["RayPool", "map_tasks", "ray_session"]

T = TypeVar("T")
R = TypeVar("R")

_POLL_S = 0.2
"""Waits on Ray are cut into slices this long, so a Ctrl-C or SIGTERM is handled at once."""


_STOP_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n))
_raised: list[BaseException] = []
"""What this process's signal handlers raised last (see ``_remembering``)."""


def _saved_signal_handlers() -> dict[int, Any]:
    """The handlers ``ray.init`` replaces (it installs its own SIGTERM handler in the driver): the
    CLI's own turn SIGTERM into a checkpoint and exit 143, so they are put back after it."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {s: signal.getsignal(s) for s in _STOP_SIGNALS}


def _remembering(handler: Callable[[int, Any], Any]) -> Callable[[int, Any], Any]:
    """``handler``, remembering what it raises. Ray's blocking calls (``ray.wait``, ``ray.get``) turn
    an exception raised by a signal handler into a plain KeyboardInterrupt; the CLI's SIGTERM handler
    raises its own (exit 143, not 130), which ``_signals_kept`` raises again."""

    def remember(signum: int, frame: Any) -> Any:
        try:
            return handler(signum, frame)
        except BaseException as err:
            _raised.append(err)
            raise

    return remember


@contextlib.contextmanager
def _signals_kept() -> Iterator[None]:
    """Around a blocking Ray call: a signal's own exception, not the KeyboardInterrupt Ray made of it."""
    _raised.clear()
    try:
        yield
    except KeyboardInterrupt as err:
        if _raised and _raised[-1] is not err:
            raise _raised[-1] from None
        raise


@contextlib.contextmanager
def ray_session(address: str, num_cpus: int) -> Iterator[Any]:
    """Connected to Ray while inside; yields the ``ray`` module.

    ``address`` "local": start a Ray instance on this machine with ``num_cpus`` CPUs, stopped on the
    way out; "auto" or HOST:PORT: join that cluster (its CPUs are the cluster's own). When this
    process is connected already (a sweep's task, a caller's own ``ray.init``), that connection is
    used and left open.
    """
    ray = require_ray()
    if ray.is_initialized():
        yield ray
        return
    address = check_ray_address(address)
    handlers = _saved_signal_handlers()
    # libsumo prints on stdout in every worker: not forwarded (workers send their errors as replies).
    options: dict[str, Any] = {"log_to_driver": False}
    if address == LOCAL:
        # Ray warns that it made a token for the instance it starts: nothing the user can act on.
        options.update(num_cpus=num_cpus, include_dashboard=False, logging_level=logging.ERROR)
    else:
        options.update(address=address, logging_level=logging.WARNING)
    try:
        ray.init(**options)
    except ConnectionError as err:
        raise InputError(f"--ray-address {address}: cannot connect to a Ray cluster: {err}") from None
    finally:
        for signum, handler in handlers.items():
            if callable(handler):
                signal.signal(signum, _remembering(handler))
            elif handler is not None:
                signal.signal(signum, handler)
    try:
        yield ray
    finally:
        try:
            ray.shutdown()
        finally:
            for signum, handler in handlers.items():
                if handler is not None:
                    signal.signal(signum, handler)


def _reason(err: BaseException) -> str:
    """The last line of a Ray error (its traceback's own conclusion), not the whole remote trace."""
    lines = [line for line in str(err).strip().splitlines() if line.strip()]
    return lines[-1].strip() if lines else type(err).__name__


class _ServerActor:
    """The actor: a ``Server`` built from its start-up value, as a ``ProcessPool`` process holds one."""

    def __init__(self, factory: str, init: Any) -> None:
        self._server = load_factory(factory)(init)

    def handle(self, request: Any, shared: Any) -> Any:
        return self._server.handle(request, shared)

    def work_ahead(self) -> None:
        run_ahead(self._server)

    def close(self) -> None:
        self._server.close()


class RayPool(WorkerPool):
    """One Ray actor (1 CPU each) per start-up value, on the cluster at ``address``."""

    def __init__(self, factory: str, inits: Sequence[Any], what: str, address: str) -> None:
        self.what = what
        self._stack = contextlib.ExitStack()
        self._ray = self._stack.enter_context(ray_session(address, num_cpus=len(inits)))
        try:
            # An actor that no node can place waits for ever: refuse what the cluster cannot hold.
            cpus = int(self._ray.cluster_resources().get("CPU", 0))
            if cpus < len(inits):
                raise InputError(
                    f"--ray-address {address}: the cluster has {cpus} CPUs, fewer than the {len(inits)} "
                    f"{what}s (one CPU each); give --workers {max(cpus, 1)} or fewer, or add nodes"
                )
            actor = self._ray.remote(num_cpus=1)(_ServerActor)
            self._actors = [actor.remote(factory, init) for init in inits]
        except BaseException:
            self._stack.close()
            raise
        self._pending: dict[int, Any] = {}

    @property
    def size(self) -> int:
        return len(self._actors)

    def submit(self, requests: Mapping[int, Any], shared: Any = None) -> None:
        # One copy in the object store for every actor of the round, not one per call.
        shared_ref = self._ray.put(shared)
        for i, request in requests.items():
            self._pending[i] = self._actors[i].handle.remote(request, shared_ref)
            # An actor runs its calls in order: this one after the reply, before the next request.
            self._actors[i].work_ahead.remote()

    def finished(self, pending: Collection[int], timeout_s: float = _POLL_S) -> list[int]:
        refs = {self._pending[i]: i for i in pending}
        with _signals_kept():
            ready, _ = self._ray.wait(list(refs), num_returns=len(refs), timeout=timeout_s)
        done = {refs[r] for r in ready}
        return [i for i in pending if i in done]

    def result(self, i: int) -> Any:
        ref = self._pending.pop(i)
        try:
            with _signals_kept():
                return self._ray.get(ref)
        except self._ray.exceptions.RayError as err:
            raise SimulationError(f"{self.what} {i} (a Ray actor) failed: {_reason(err)}") from None

    def close(self) -> None:
        try:
            closing = [a.close.remote() for a in self._actors]
            with contextlib.suppress(self._ray.exceptions.RayError), _signals_kept():
                self._ray.get(closing, timeout=CLOSE_TIMEOUT_S)
        finally:
            self.kill()

    def kill(self) -> None:
        try:
            for actor in self._actors:
                with contextlib.suppress(Exception):
                    self._ray.kill(actor)
            self._actors, self._pending = [], {}
        finally:
            self._stack.close()


def map_tasks(
    function: Callable[[T], R],
    items: Sequence[T],
    num_cpus: int,
    on_done: Callable[[int, R], None] | None = None,
) -> list[R]:
    """``function`` on each item as a Ray task reserving ``num_cpus`` CPUs (the caller is connected:
    ``ray_session``); the results in item order. ``on_done(i, result)`` as each one finishes. An
    idas-sumo error in a task is raised here as itself."""
    ray = require_ray()
    remote = ray.remote(num_cpus=num_cpus, max_retries=0)(function)
    refs = [remote.remote(item) for item in items]
    index = {ref: i for i, ref in enumerate(refs)}
    results: dict[int, R] = {}
    try:
        pending = list(refs)
        while pending:
            with _signals_kept():
                ready, pending = ray.wait(pending, num_returns=1, timeout=_POLL_S)
            for ref in ready:
                i = index[ref]
                try:
                    with _signals_kept():
                        results[i] = ray.get(ref)
                except ray.exceptions.RayTaskError as err:
                    cause = getattr(err, "cause", None)
                    if isinstance(cause, IdasError):
                        raise cause from None
                    raise SimulationError(f"run {i} failed on Ray: {_reason(err)}") from None
                except ray.exceptions.RayError as err:
                    raise SimulationError(f"run {i} failed on Ray: {_reason(err)}") from None
                if on_done is not None:
                    on_done(i, results[i])
    except BaseException:
        for ref in refs:
            with contextlib.suppress(Exception):
                ray.cancel(ref, force=True)
        raise
    return [results[i] for i in range(len(items))]
