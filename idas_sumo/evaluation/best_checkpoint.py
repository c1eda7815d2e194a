"""One training checkpoint on the paper suite: what ``idas-sumo sweep --evaluate`` adds to each run's row.

Here, not in training/sweep.py, because evaluation and training sit on one layer and do not import each
other: the command line hands this function to the sweep.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from idas_sumo.evaluation.runner import EvalRequest, run_evaluation
from idas_sumo.sim.merge_detect import MergeSite

__all__ = ["evaluate_checkpoint"]


def evaluate_checkpoint(
    checkpoint: Path, site: MergeSite, out: Path, *, seed: int, scenarios: int
) -> dict[str, Any]:
    """``checkpoint`` as the IDAS policy on the run's merge ``site``, ``scenarios`` paper-suite scenarios
    drawn with ``seed`` (the other cars as ``evaluate`` drives them by default); the CSVs go to ``out``
    (replaced), and the summary's percentages come back as ``eval_*`` columns."""
    result = run_evaluation(
        EvalRequest(
            net=site.path,
            site=site,
            methods=("idas",),
            seed=seed,
            scenarios=scenarios,
            policy=checkpoint,
            out=out,
            force=True,
            progress=False,
        )
    )
    summary = result.summary.iloc[0]
    return {
        "eval_seed": seed,
        "eval_scenarios": int(summary["scenarios"]),
        "eval_success_pct": float(summary["success_pct"]),
        "eval_perfect_pct": float(summary["perfect_pct"]),
        "eval_collision_pct": float(summary["collision_pct"]),
    }
