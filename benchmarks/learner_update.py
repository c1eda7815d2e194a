"""Learner update speed: the plain formulation against the one training uses, in the same run.

    python benchmarks/learner_update.py [--rows 8000] [--threads 1 2] [--repeats 3]

One stage-2 update (V, Q and actor) on a batch of ``--rows`` agent-steps shaped like a rollout's (agents of 100
steps linked by ``next_row``, grids with cars: runs of 11 equal cells, as the env draws them), timed as the median
of ``--repeats`` after a warm-up:

* *plain*: the encoder as written in the paper's terms (``GridEncoder.reference_forward``: conv2d, flatten,
  cat, Linear) and V(o') by its own forward pass on ``next_obs`` (``next_row`` left out);
* *fast*: what training runs (``GridEncoder.forward`` on the learner's ``ObsWindows``: the conv from the grids'
  runs and the first joint layer over the blocks of cells the cars reach, agents/run_conv.py and
  agents/run_blocks.py; V(o') read from the next row's V(o)).
"""

from __future__ import annotations

import idas_sumo  # noqa: F401  (first: its OMP_WAIT_POLICY must be set before torch loads)

# isort: split
import argparse
import dataclasses
import statistics
import time
from collections.abc import Iterator
from contextlib import contextmanager

import torch
from rich.console import Console
from rich.table import Table

from idas_sumo.agents.critic_input import OTHERS_ACTIONS_DIM
from idas_sumo.agents.learner import Batch, Learner, LearnerConfig
from idas_sumo.agents.networks import GridEncoder, ObsWindows
from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.layout import GRID_CELLS, N_SCALARS, OBS_DIM
from idas_sumo.env.state_layout import STATE_DIM, STATE_SLOTS

AGENT_STEPS = 100
"""Rows per agent in the synthetic batch (an agent's rows are linked by next_row)."""
CARS_PER_ROW = 4
CAR_CELLS = 11


def rollout_like_batch(rows: int, seed: int = 0) -> Batch:
    g = torch.Generator().manual_seed(seed)
    obs = torch.zeros(rows + 1, OBS_DIM)
    obs[:, :N_SCALARS] = torch.randn(rows + 1, N_SCALARS, generator=g)
    # About 5.5 runs per observation, as in a stage-2 round of the shipped policy: cars of 11 cells on the
    # four grid rows (occupancy 1, a relative speed), some of them out of view.
    grids = obs[:, N_SCALARS:].view(rows + 1, 4, GRID_CELLS)
    for _ in range(CARS_PER_ROW):
        lane_row = 2 * torch.randint(0, 2, (rows + 1,), generator=g)
        first = torch.randint(0, GRID_CELLS - CAR_CELLS, (rows + 1,), generator=g)
        speed = torch.rand(rows + 1, generator=g) - 0.5
        seen = torch.rand(rows + 1, generator=g) < 0.7
        for cell in range(CAR_CELLS):
            at = (torch.arange(rows + 1), lane_row, first + cell)
            grids[at] = torch.where(seen, 1.0, grids[at])
            grids[(at[0], at[1] + 1, at[2])] = torch.where(seen, speed, grids[(at[0], at[1] + 1, at[2])])
    index = torch.arange(rows)
    last = (index % AGENT_STEPS) == AGENT_STEPS - 1
    next_row = torch.where(last, -1, index + 1)
    done = (last & (index % (2 * AGENT_STEPS) == AGENT_STEPS - 1)).float()  # every other agent finishes
    next_obs = torch.where(last[:, None], obs[rows], obs[(index + 1).clamp(max=rows - 1)])
    next_obs[done.bool()] = 0.0
    return Batch(
        obs=obs[:rows],
        mask=torch.ones(rows, N_ACTIONS, dtype=torch.bool),
        action=torch.randint(0, N_ACTIONS, (rows,), generator=g),
        reward=torch.randn(rows, generator=g),
        next_obs=next_obs,
        done=done,
        state=torch.randn(rows, STATE_DIM, generator=g),
        others_actions=torch.zeros(rows, OTHERS_ACTIONS_DIM),
        slot=torch.randint(0, STATE_SLOTS, (rows,), generator=g),
        joint_reward=torch.randn(rows, generator=g),
        next_state=torch.randn(rows, STATE_DIM, generator=g),
        next_others_actions=torch.zeros(rows, OTHERS_ACTIONS_DIM),
        next_slot=torch.randint(0, STATE_SLOTS, (rows,), generator=g),
        next_action=torch.randint(0, N_ACTIONS, (rows,), generator=g),
        next_valid=(next_row >= 0).float(),
        next_row=next_row,
    )


@contextmanager
def plain_encoder() -> Iterator[None]:
    fast = GridEncoder.forward

    def plain(self: GridEncoder, obs: torch.Tensor | ObsWindows) -> torch.Tensor:
        # The learner hands its networks the batch with its runs found (ObsWindows); the plain path reads the rows.
        return self.reference_forward(obs.obs if isinstance(obs, ObsWindows) else obs)

    GridEncoder.forward = plain  # type: ignore[method-assign]
    try:
        yield
    finally:
        GridEncoder.forward = fast  # type: ignore[method-assign]


def seconds_per_update(batch: Batch, plain: bool, repeats: int) -> float:
    learner = Learner(LearnerConfig(use_central_critic=True))
    if plain:
        batch = dataclasses.replace(batch, next_row=None)
    times = []
    for i in range(repeats + 1):
        start = time.perf_counter()
        if plain:
            with plain_encoder():
                learner.update(batch)
        else:
            learner.update(batch)
        if i:  # the first is a warm-up
            times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--rows", type=int, default=8000, help="agent-steps per update")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    batch = rollout_like_batch(args.rows)
    table = Table(title=f"one stage-2 learner update on {args.rows:,} agent-steps (median of {args.repeats})")
    for col in ("threads", "plain s", "fast s", "plain agent-steps/s", "fast agent-steps/s", "speed-up"):
        table.add_column(col, justify="right")
    for threads in args.threads:
        torch.set_num_threads(threads)
        # Interleaved per thread count so a drift in machine load hits both.
        plain = seconds_per_update(batch, True, args.repeats)
        fast = seconds_per_update(batch, False, args.repeats)
        table.add_row(
            str(threads),
            f"{plain:.2f}",
            f"{fast:.2f}",
            f"{args.rows / plain:,.0f}",
            f"{args.rows / fast:,.0f}",
            f"{plain / fast:.2f}x",
        )
    Console(width=120).print(table)


if __name__ == "__main__":
    main()
