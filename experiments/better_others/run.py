"""The headline protocol with other cars that negotiate better among their own kind (issue 36, after
experiments/ego_ceiling).

The paper evaluates each method as the ego among cars driven by "the learned IDAS policy" (L322); ``evaluate`` drives
them with the shipped ``idas.pt``. This script runs the same protocol (``suite_cases``, ``run_jobs``, the default
``EvalConfig``, greedy policies) with the other cars on another IDAS checkpoint (``--others LABEL=PATH``, repeated),
and each ego method (``--ego LABEL=PATH`` for a checkpoint, or a method name: ``warm_start``, ``idm``, ...; the
label ``self`` runs the others' own checkpoint as the ego, i.e. every car on it).

Writes ``episodes.csv`` (``evaluate``'s rows plus an ``others`` column) and prints, per ``others``: each ego's
success and perfect %, the union of perfect scenarios, and the paired margin of ``self`` over each other ego.

    python experiments/better_others/run.py --seed 2035 --out results/better_others \\
        --others shipped=idas_sumo/policies/idas.pt --ego self --ego warm_start --ego idm --ego fsm_idm
"""

from __future__ import annotations

import idas_sumo  # noqa: F401  (first: its OMP_WAIT_POLICY must be set before torch loads)

# isort: split
import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from idas_sumo.env.contracts import Policy
from idas_sumo.env.engine import MergeEngine
from idas_sumo.evaluation.policies import learned_policy, resolve_policy
from idas_sumo.evaluation.protocol import eval_jobs, run_jobs

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "ego_ceiling"))
from search import headline_cases  # the headline's cases, built as the ceiling search builds them

COPIES = 16


def _labelled(spec: str) -> tuple[str, Path]:
    label, _, path = spec.partition("=")
    if not path:
        raise SystemExit(f"expected LABEL=PATH, got {spec!r}")
    return label, Path(path)


def _egos(specs: list[str], others: Path, seed: int) -> dict[str, Policy]:
    egos: dict[str, Policy] = {}
    for spec in specs:
        if spec == "self":
            egos["self"] = learned_policy(others, seed)
        elif "=" in spec:
            label, path = _labelled(spec)
            egos[label] = learned_policy(path, seed)
        else:
            egos[spec] = resolve_policy(spec, None, seed)
    return egos


def _margins(frame: pd.DataFrame) -> pd.DataFrame:
    """Per ego: success %, perfect %, and ``self``'s paired margin on perfect success (points, standard error)."""
    perfect = frame.pivot(index="scenario", columns="method", values="perfect")
    rows = []
    for ego, group in frame.groupby("method", sort=False):
        diff = perfect["self"] - perfect[ego] if "self" in perfect else None
        rows.append(
            {
                "ego": ego,
                "success_pct": 100 * group["success"].mean(),
                "perfect_pct": 100 * group["perfect"].mean(),
                "self_minus_pts": None if diff is None else 100 * diff.mean(),
                "se_pts": None if diff is None else 100 * diff.std(ddof=1) / np.sqrt(len(diff)),
            }
        )
    rows.append({"ego": "any ego", "perfect_pct": 100 * perfect.max(axis=1).mean()})
    return pd.DataFrame(rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--scenarios", type=int, default=100)
    parser.add_argument("--others", action="append", required=True, help="LABEL=PATH of an IDAS checkpoint")
    parser.add_argument("--ego", action="append", required=True)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    site, config, cases = headline_cases(args.seed, args.scenarios)
    frames = []
    for spec in args.others:
        label, path = _labelled(spec)
        egos = _egos(args.ego, path, args.seed)
        engine = MergeEngine(site, copies=COPIES, seed=args.seed, config=config.env)
        try:
            rows = [
                r.episode
                for _, r in run_jobs(engine, eval_jobs(cases, list(egos)), egos, learned_policy(path))
            ]
        finally:
            engine.close()
        frame = pd.DataFrame(rows).assign(others=label)
        frames.append(frame)
        print(f"\nothers: {label} ({path})")
        print(_margins(frame).round(2).to_string(index=False), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    pd.concat(frames, ignore_index=True).to_csv(args.out / "episodes.csv", index=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
