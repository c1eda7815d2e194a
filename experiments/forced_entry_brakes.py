"""How many paper-suite scenarios hold a hard brake that a car's own mask forces on it before it could choose
(issue 36, item 2), for each way of drawing later entries (``[traffic] entries``: "as_drawn", the shipped
results'; "feasible", the default).

Runs ``idas-sumo evaluate`` on the paper suite (100 scenarios, seed 2019, the own-lane mask unless
``--safety-mask`` says otherwise) with ``--trajectories`` once per option, then reads every car's decisions:
a forced brake is a step whose mask allows the hard brake alone. Counted per car, as two readings:

- ``first_0.4s``: a forced brake in the car's first two decision steps (the issue's measure: "in a car's
  first 0.4 s after a staggered entry, before any decision of its own" - its first step's Δa choices all
  lead there);
- ``before_free``: a forced brake before the car's first step with a Δa action allowed.

A scenario counts when any of its cars has one. Usage (about a minute per option and method on 2 cores):

    python experiments/forced_entry_brakes.py [--baseline idm] [--others idm] [--out results/forced_entry]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pandas as pd

from idas_sumo.resources import SCENARIO_DIR

ENTRIES = ("as_drawn", "feasible")
FORCED = "0000010"  # the mask column of trajectories.csv: only the hard brake (action 5) allowed
FIRST_STEPS = 2  # 0.4 s


def config_with(entries: str, out: Path) -> Path:
    """The paper suite's config (scenarios/eval_paper.toml) with ``entries`` set."""
    text = (SCENARIO_DIR / "eval_paper.toml").read_text(encoding="utf-8")
    lines = [line for line in text.splitlines() if not line.startswith("entries")]
    at = lines.index("[traffic]") + 1
    lines.insert(at, f'entries = "{entries}"')
    path = out / f"eval_paper_{entries}.toml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def forced_cars(trajectories: Path) -> pd.DataFrame:
    """One row per car: when it first decided, and whether a forced brake came first (both readings)."""
    df = pd.read_csv(trajectories, dtype={"allowed_actions": str})
    decided = df[df.action >= 0].sort_values(["scenario", "vehicle", "time_s"], kind="stable")
    rows = []
    for (scenario, vehicle), steps in decided.groupby(["scenario", "vehicle"], sort=False):
        masks = steps.allowed_actions.tolist()
        forced = [m == FORCED for m in masks]
        free = [("1" in m[:5]) for m in masks]
        first_free = free.index(True) if True in free else len(masks)
        rows.append(
            {
                "scenario": scenario,
                "vehicle": vehicle,
                "first_decision_s": float(steps.time_s.iloc[0]),
                "first_0.4s": any(forced[:FIRST_STEPS]),
                "before_free": any(forced[:first_free]),
            }
        )
    return pd.DataFrame(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default="idm")
    parser.add_argument("--others", default="idm")
    parser.add_argument("--safety-mask", default="own_lane", choices=("own_lane", "merge_aware"))
    parser.add_argument("--scenarios", type=int, default=100)
    parser.add_argument("--seed", type=int, default=2019)
    parser.add_argument("--out", type=Path, default=Path("results/forced_entry"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    table = []
    for entries in ENTRIES:
        run = args.out / f"{args.baseline}-{args.others}-{args.safety_mask}-{entries}"
        command = [
            *(sys.executable, "-m", "idas_sumo.cli", "evaluate"),
            *("--baseline", args.baseline, "--others", args.others, "--safety-mask", args.safety_mask),
            *("--scenarios", str(args.scenarios), "--seed", str(args.seed)),
            *("--config", str(config_with(entries, args.out)), "--out", str(run)),
            *("--trajectories", "--no-progress", "--force"),
        ]
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        cars = forced_cars(run / "trajectories.csv")
        later = cars.first_decision_s > 0.2 + 1e-9  # entered after the first step
        for reading in ("first_0.4s", "before_free"):
            hit = cars[reading]
            table.append(
                {
                    "entries": entries,
                    "reading": reading,
                    "scenarios": int(cars[hit].scenario.nunique()),
                    "cars": int(hit.sum()),
                    "of_them_later_entries": int((hit & later).sum()),
                }
            )
    result = pd.DataFrame(table)
    result.to_csv(args.out / f"counts-{args.baseline}-{args.others}-{args.safety_mask}.csv", index=False)
    print(
        f"{args.scenarios} paper-suite scenarios, seed {args.seed}, {args.baseline} / others {args.others}, "
        f"{args.safety_mask} mask"
    )
    print(result.to_string(index=False))


if __name__ == "__main__":
    main()
