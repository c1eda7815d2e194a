"""The tables of experiments/validation_failures/README.md, from the CSVs that run.sh writes.

python experiments/validation_failures/tables.py [RESULTS]   # default experiments/validation_failures/results
"""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd

RUNS = ("seed123", "seed123_merge_aware", "seed123_60s", "seed777", "seed777_merge_aware", "seed777_60s")
RUNS_AS_DRAWN = ("seed777_as_drawn",)


def outcomes(results: Path) -> pd.DataFrame:
    """Per run and method: success / perfect %, timeouts, collision scenarios, unfinishable scenarios failed."""
    rows = []
    for run in (*RUNS, *RUNS_AS_DRAWN):
        summary = pd.read_csv(results / run / "summary.csv")
        for r in summary.itertuples():
            rows.append(
                {
                    "run": run,
                    "method": r.method,
                    "success %": round(100 * r.success, 1),
                    "perfect %": round(100 * r.perfect, 1),
                    "timeouts": r.timeouts,
                    "collision scen.": r.collision_scenarios,
                    "failed unfinishable": f"{r.failed_unfinishable} of {r.scenarios - r.finishable_scenarios}",
                    "success % of finishable": round(100 * r.success_of_finishable, 1),
                    "perfect % of finishable": round(100 * r.perfect_of_finishable, 1),
                }
            )
    return pd.DataFrame(rows)


def imperfect(results: Path, run: str) -> pd.DataFrame:
    """Finishable scenarios that succeeded without being perfect: what their hard brakes were."""
    episodes = pd.read_csv(results / run / "episodes.csv")
    scenarios = pd.read_csv(results / run / "scenarios.csv")
    brakes = pd.read_csv(results / run / "brakes.csv")
    finishable = set(scenarios[scenarios.finishable_alone].scenario)
    rows = []
    for method, e in episodes[episodes.scenario.isin(finishable)].groupby("method", sort=False):
        imp = e[(e.success == 1) & (e.perfect == 0)]
        b = brakes[(brakes.method == method) & brakes.scenario.isin(imp.scenario)]
        rows.append(
            {
                "method": method,
                "success, not perfect": len(imp),
                "with a chosen brake": int((imp.hard_brakes > imp.forced_hard_brakes).sum()),
                "forced brakes only": int(
                    ((imp.hard_brakes == imp.forced_hard_brakes) & (imp.hard_brakes > 0)).sum()
                ),
                "forced before free": int((imp.cars_forced_before_free > 0).sum()),
                "brake onsets": len(b),
                "forced": int(b.forced.sum()),
                "car ahead from other road": int(b.ahead_other_road.fillna(0).sum()),
                "had Δa in last 1 s": int((b.free_steps_last_second > 0).sum()),
            }
        )
    return pd.DataFrame(rows)


def main() -> None:
    results = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parent / "results"
    with pd.option_context("display.width", 250, "display.max_columns", 20):
        print(outcomes(results).to_string(index=False))
        for run in ("seed123", "seed777", "seed777_merge_aware"):
            print(f"\n{run}: successes that are not perfect (finishable scenarios)")
            print(imperfect(results, run).to_string(index=False))
        for name in ("paper_warm_start", "paper_intelligent"):
            print(f"\n{name} (idas-sumo evaluate, seed 777, 200 scenarios)")
            print(pd.read_csv(results / name / "summary.csv").to_string(index=False))


if __name__ == "__main__":
    main()
