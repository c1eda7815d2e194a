"""Rollout workers: where episodes are collected. The loop only sees ``RolloutWorkers.run``.

``InProcessWorkers`` runs the episodes in the training process. ``ProcessWorkers`` starts W
processes (fresh interpreters: libsumo allows one SUMO per process, and a forked SUMO is not safe), each with its
own episode engine (env/engine.py: ``copies`` episodes side by side in one SUMO run, one actor
forward per step for all of them); every round they get the current actor weights and a share of the
episodes.
Each episode carries its own action-sampling seed, so the data do not depend on the worker count or
on which worker ran which episode. A Ray or other cluster backend would be one more implementation of
``RolloutWorkers``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import signal
import subprocess
import sys
import threading
import time
import traceback
from abc import ABC, abstractmethod
from dataclasses import dataclass
from multiprocessing.connection import Connection, Listener
from pathlib import Path
from types import TracebackType

import numpy as np
import torch

from idas_sumo.agents.learner import Learner, LearnerConfig
from idas_sumo.agents.rollout import EpisodeData, RolloutTask, collect_episodes
from idas_sumo.env.engine import EnvConfig, MergeEngine
from idas_sumo.errors import IdasError, SimulationError

__all__ = ["EpisodeTask", "InProcessWorkers", "ProcessWorkers", "RolloutWorkers", "make_workers"]

log = logging.getLogger(__name__)

ActorWeights = dict[str, np.ndarray]


EpisodeTask = RolloutTask
"""One episode to collect: the scenario, the seed of its action sampling, greedy (validation) or not."""


def actor_weights(learner: Learner) -> ActorWeights:
    """The actor's weights as numpy arrays (cheap to pickle to another process)."""
    return {k: v.detach().cpu().numpy().copy() for k, v in learner.actor.state_dict().items()}


def _run_tasks(engine: MergeEngine, learner: Learner, tasks: list[EpisodeTask]) -> list[EpisodeData]:
    return collect_episodes(engine, learner, tasks)


class RolloutWorkers(ABC):
    """Collects episodes with given actor weights; results come back in task order."""

    @abstractmethod
    def run(self, learner: Learner, tasks: list[EpisodeTask]) -> list[EpisodeData]: ...

    @abstractmethod
    def close(self) -> None: ...

    def __enter__(self) -> RolloutWorkers:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


class InProcessWorkers(RolloutWorkers):
    """Collect in this process, with the learner's own actor."""

    def __init__(
        self, net_path: Path, env_config: EnvConfig, seed: int, copies: int, gui: bool = False
    ) -> None:
        copies = 1 if gui else copies
        self.engine = MergeEngine(net_path, copies=copies, seed=seed, config=env_config, gui=gui)

    def run(self, learner: Learner, tasks: list[EpisodeTask]) -> list[EpisodeData]:
        # Small-batch inference is ~4x slower with intra-op threads fighting SUMO (measured, 2 cores);
        # the learner update afterwards gets the threads back.
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            return _run_tasks(self.engine, learner, tasks)
        finally:
            torch.set_num_threads(threads)

    def close(self) -> None:
        self.engine.close()


@dataclass
class _PackedEpisode:
    """An episode for the pipe: observations sparse (~4 % non-zero), next-step copies dropped."""

    episode: EpisodeData
    obs_shape: tuple[int, int]
    obs_flat_index: np.ndarray
    obs_values: np.ndarray


def _pack(e: EpisodeData) -> _PackedEpisode:
    flat = e.obs_bank.reshape(-1)
    index = np.flatnonzero(flat).astype(np.int32 if flat.size < 2**31 else np.int64)
    empty = np.zeros(0, dtype=np.float32)
    light = dataclasses.replace(
        e,
        obs_bank=empty.reshape(0, e.obs_bank.shape[1]),
        next_state=empty,
        next_others_actions=empty,
        next_slot=empty.astype(np.int64),
        next_action=empty.astype(np.int64),
    )
    return _PackedEpisode(light, (int(e.obs_bank.shape[0]), int(e.obs_bank.shape[1])), index, flat[index])


def _unpack(p: _PackedEpisode) -> EpisodeData:
    e = p.episode
    obs = np.zeros(p.obs_shape[0] * p.obs_shape[1], dtype=np.float32)
    obs[p.obs_flat_index] = p.obs_values
    valid = e.next_row >= 0
    nxt = e.next_row[valid]
    next_state = np.zeros_like(e.state)
    next_others = np.zeros_like(e.others_actions)
    next_slot = np.zeros_like(e.slot)
    next_action = np.zeros_like(e.action)
    next_state[valid] = e.state[nxt]
    next_others[valid] = e.others_actions[nxt]
    next_slot[valid] = e.slot[nxt]
    next_action[valid] = e.action[nxt]
    return dataclasses.replace(
        e,
        obs_bank=obs.reshape(p.obs_shape),
        next_state=next_state,
        next_others_actions=next_others,
        next_slot=next_slot,
        next_action=next_action,
    )


def _worker_main(conn: Connection, net_path: str, env_config: EnvConfig, seed: int, copies: int) -> None:
    """A worker process: owns one SUMO; answers ('run', weights, tasks) until ('close',)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    torch.set_num_threads(1)
    engine: MergeEngine | None = None
    try:
        engine = MergeEngine(net_path, copies=copies, seed=seed, config=env_config)
        learner = Learner(LearnerConfig(), seed=0)
        while True:
            msg = conn.recv()
            if msg[0] == "close":
                break
            _, weights, tasks = msg
            try:
                learner.actor.load_state_dict({k: torch.from_numpy(v) for k, v in weights.items()})
                conn.send(("ok", [_pack(e) for e in _run_tasks(engine, learner, tasks)]))
            except IdasError as err:
                conn.send(("error", type(err).__name__, str(err)))
            except Exception:
                conn.send(("error", "Exception", traceback.format_exc()))
    except (EOFError, BrokenPipeError):
        pass
    finally:
        if engine is not None:
            engine.close()


_CHILD_CODE = (
    "import sys; sys.path.append(sys.argv[1]); "
    "from idas_sumo.training.workers import _child_main; _child_main(sys.argv[2], int(sys.argv[3]))"
)
_CONNECT_TIMEOUT_S = 120.0
"""How long a starting worker may take to import torch and call back before the run gives up."""


def _child_main(host: str, port: int) -> None:
    """A worker started by ``ProcessWorkers``: read the authkey on stdin, call back, serve."""
    from multiprocessing.connection import Client

    authkey = sys.stdin.buffer.read()
    conn = Client((host, port), authkey=authkey)
    net_path, env_config, seed, copies = conn.recv()
    _worker_main(conn, net_path, env_config, seed, copies)


class ProcessWorkers(RolloutWorkers):
    """W worker processes, one SUMO each; a round splits the tasks into W contiguous shares.

    Workers are fresh interpreters started with subprocess (as evaluation/workers.py and
    sim/backend.py start theirs), not multiprocessing's spawn: that re-imports the user's
    ``__main__``, so a script calling ``run_training`` without an ``if __name__ == "__main__":``
    guard would run itself again. Each worker calls back on a loopback socket that only holders
    of a fresh random key (sent on its stdin, not its command line) can use.
    """

    def __init__(self, net_path: Path, env_config: EnvConfig, seed: int, workers: int, copies: int) -> None:
        self._conns: list[Connection] = []
        self._procs: list[subprocess.Popen[bytes]] = []
        authkey = os.urandom(32)
        package_root = str(Path(__file__).resolve().parents[2])
        try:
            with Listener(("127.0.0.1", 0), authkey=authkey) as listener:
                host, port = listener.address
                for _ in range(workers):
                    proc = subprocess.Popen(
                        [sys.executable, "-P", "-c", _CHILD_CODE, package_root, host, str(port)],
                        stdin=subprocess.PIPE,
                        stdout=subprocess.DEVNULL,  # libsumo prints on stdout
                        start_new_session=True,  # Ctrl-C is the parent's to handle
                    )
                    assert proc.stdin is not None
                    proc.stdin.write(authkey)
                    proc.stdin.close()
                    self._procs.append(proc)
                for w in range(workers):
                    conn = self._accept(listener)
                    conn.send((str(net_path), env_config, seed + 1 + w, copies))
                    self._conns.append(conn)
        except BaseException:
            self.close()
            raise

    def _accept(self, listener: Listener) -> Connection:
        """The next worker's authenticated connection; an error if the workers die or never call."""
        result: list[Connection | BaseException] = []

        def accept() -> None:
            try:
                result.append(listener.accept())
            except BaseException as err:  # handed to the waiting thread
                result.append(err)

        thread = threading.Thread(target=accept, daemon=True)
        thread.start()
        deadline = time.monotonic() + _CONNECT_TIMEOUT_S
        while thread.is_alive():
            thread.join(timeout=0.2)
            if thread.is_alive() and (
                time.monotonic() > deadline or all(p.poll() is not None for p in self._procs)
            ):
                raise SimulationError("a rollout worker failed to start (see its error above)")
        if isinstance(result[0], BaseException):
            raise SimulationError(f"a rollout worker failed to connect: {result[0]}")
        return result[0]

    def run(self, learner: Learner, tasks: list[EpisodeTask]) -> list[EpisodeData]:
        weights = actor_weights(learner)
        shares = [list(s) for s in np.array_split(np.arange(len(tasks)), len(self._conns))]
        busy = []
        for conn, idx in zip(self._conns, shares, strict=True):
            if idx:
                try:
                    conn.send(("run", weights, [tasks[i] for i in idx]))
                except (BrokenPipeError, EOFError, OSError):
                    raise SimulationError("a rollout worker died (see its error above)") from None
                busy.append(conn)
        results: list[EpisodeData] = []
        errors: list[str] = []
        for conn in busy:  # in order, so results follow the task order
            try:
                reply = conn.recv()
            except EOFError:
                errors.append("a rollout worker died")
                continue
            if reply[0] == "ok":
                results.extend(_unpack(p) for p in reply[1])
            else:
                errors.append(f"{reply[1]}: {reply[2]}")
        if errors:
            raise SimulationError(f"rollout worker failed: {errors[0]}")
        return results

    def close(self) -> None:
        for conn in self._conns:
            with contextlib.suppress(BrokenPipeError, OSError):
                conn.send(("close",))
        for proc in self._procs:
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                log.warning("rollout worker %s did not stop; killing it", proc.pid)
                proc.kill()
                proc.wait()
        for conn in self._conns:
            conn.close()
        self._conns = []
        self._procs = []


def make_workers(
    net_path: Path, env_config: EnvConfig, seed: int, workers: int, copies: int, gui: bool = False
) -> RolloutWorkers:
    """``workers`` processes (1: this one), each running ``copies`` episodes side by side."""
    if workers <= 1:
        return InProcessWorkers(net_path, env_config, seed, copies, gui=gui)
    return ProcessWorkers(net_path, env_config, seed, workers, copies)
