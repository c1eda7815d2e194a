"""How many rollout workers a run starts: one rule for ``TrainConfig.rollout_workers`` and for ``idas-sumo
train``, which starts them while it imports the trainer (this module imports no torch)."""

from __future__ import annotations

from idas_sumo.sim.processes import max_workers

__all__ = ["EPISODES_PER_WORKER", "ROLLOUT_PRELOAD", "ROLLOUT_SERVER_MODULE", "rollout_workers"]

ROLLOUT_SERVER_MODULE = "idas_sumo.training.workers"
"""Where a rollout worker's server lives (``RolloutServer``): what a worker started early imports first."""
ROLLOUT_PRELOAD = f"{ROLLOUT_SERVER_MODULE}:warm_up"
"""What the workers' fork server imports and runs before it forks them (``sim.processes.worker_fork_server``)."""

EPISODES_PER_WORKER = 8
"""With ``workers = 0``, a round's episodes per rollout process at least: a step's fixed costs (the engine's
Python, SUMO's step, the actor's call) are shared by the episodes a process runs side by side, so a process
with fewer would not earn its start (8 episodes of a stage-2 round took 0.6 of the CPU time of 16 in one
process, docs/performance.md)."""


def rollout_workers(workers: int, episodes_per_update: int, budget: int, gui: bool = False) -> int:
    """``workers``, or for 0 one per CPU this process may use (``max_workers``) and per ``EPISODES_PER_WORKER``
    episodes of a round (``episodes_per_update``, or the stages' largest ``budget`` if that is shorter), at least
    one; 1 with ``gui`` (the rollouts show in one window)."""
    if workers:
        return workers
    round_size = min(episodes_per_update, budget)
    return 1 if gui else max(1, min(max_workers(), round_size // EPISODES_PER_WORKER))
