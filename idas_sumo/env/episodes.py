"""The one episode loop: fill the engine's slots with the next scenarios, step until all are over, refill."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Protocol

import numpy as np

from idas_sumo import stops
from idas_sumo.env.contracts import AgentBatch, IntArray, Policy, StepResult
from idas_sumo.env.outcome import EpisodeOutcome
from idas_sumo.env.scenario import Scenario

if TYPE_CHECKING:
    from idas_sumo.env.engine import MergeEngine


class EpisodeObserver(Protocol):
    """Hooks of ``run_episodes``; ``job`` is the scenario's index in the list given to it."""

    def decided(self, engine: MergeEngine, jobs: Sequence[int], batch: AgentBatch, actions: IntArray) -> None:
        """Before a step: the actions chosen for ``batch`` (``jobs[k]``: the job in slot k)."""

    def stepped(
        self,
        engine: MergeEngine,
        jobs: Sequence[int],
        batch: AgentBatch,
        actions: IntArray,
        result: StepResult,
    ) -> None:
        """After the step."""

    def ended(self, engine: MergeEngine, slot: int, job: int, outcome: EpisodeOutcome) -> None:
        """Slot ``slot``'s episode (job ``job``) is over; ``engine.snapshot`` still shows its last state."""


AssignPolicy = Callable[[int, str], int]
"""(job, agent id) -> index of the policy that drives that agent."""


def iter_episodes(
    engine: MergeEngine,
    scenarios: Sequence[Scenario],
    assign_policy: AssignPolicy,
    policies: Sequence[Policy],
    observer: EpisodeObserver | None = None,
    sumo_args: Callable[[int], Sequence[str]] | None = None,
) -> Iterator[tuple[int, EpisodeOutcome]]:
    """Run every scenario to its end, ``engine.copies`` at a time; yield (job, outcome) in job order.

    ``sumo_args(job)``: SUMO options for that job's run (only with one copy: a run holds all copies).
    """
    if sumo_args is not None and engine.copies != 1:
        raise ValueError("per-scenario SUMO options need an engine with one copy")
    k_max = engine.copies
    for start in range(0, len(scenarios), k_max):
        jobs = list(range(start, min(start + k_max, len(scenarios))))
        args = sumo_args(jobs[0]) if sumo_args is not None else ()
        engine.reset([scenarios[j] for j in jobs], args)
        assigned: list[dict[str, int]] = [{} for _ in jobs]
        reported: set[int] = set()
        while True:
            for k in range(len(jobs)):
                if k not in reported and engine.over(k):
                    reported.add(k)
                    if observer is not None:
                        observer.ended(engine, k, jobs[k], engine.outcome(k))
                    engine.release_slot(k)
            if len(reported) == len(jobs):
                break
            stops.check()
            batch = engine.observe()
            batch.job = np.asarray(jobs, dtype=np.int64)[batch.copy]
            actions = np.zeros(len(batch), dtype=np.int64)
            if len(batch):
                which = np.empty(len(batch), dtype=np.int64)
                for i, (a, k) in enumerate(zip(batch.ids, batch.copy.tolist(), strict=True)):
                    p = assigned[k].get(a)
                    if p is None:
                        p = assigned[k][a] = assign_policy(jobs[k], a)
                    which[i] = p
                for p in np.unique(which).tolist():
                    rows = np.flatnonzero(which == p)
                    actions[rows] = policies[p].act(batch, rows)
            if observer is not None:
                observer.decided(engine, jobs, batch, actions)
            result = engine.step(actions)
            if observer is not None:
                observer.stepped(engine, jobs, batch, actions, result)
        for k, j in enumerate(jobs):
            yield j, engine.outcome(k)


def run_episodes(
    engine: MergeEngine,
    scenarios: Sequence[Scenario],
    assign_policy: AssignPolicy,
    policies: Sequence[Policy],
    observer: EpisodeObserver | None = None,
    sumo_args: Callable[[int], Sequence[str]] | None = None,
) -> list[EpisodeOutcome]:
    """Every scenario's outcome, in scenario order (``iter_episodes``)."""
    return [o for _, o in iter_episodes(engine, scenarios, assign_policy, policies, observer, sumo_args)]
