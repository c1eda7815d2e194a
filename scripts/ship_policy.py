"""Copy a training checkpoint into the package's idas_sumo/policies/ and write the metadata that says how it was made.

    python scripts/ship_policy.py runs/idas/intelligent.pt idas --command "idas-sumo train ..."

Writes idas_sumo/policies/NAME.pt (the checkpoint, loadable by ``idas-sumo evaluate --baseline NAME``)
and idas_sumo/policies/NAME.json: config, episodes per stage, seed, wall time, end-of-stage learning-curve numbers,
package versions. With ``--budget-run DIR`` (the same seed and config run on a larger budget, whose first episodes
are the checkpoint's run's: validation never touches the training generators) the metadata also records that run's
episodes, end-of-stage numbers and validation curve, after checking row by row that its first episodes are the
checkpoint run's; a run that differs is refused.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import os
import platform
import shutil
import sys
from importlib import metadata
from pathlib import Path

import pandas as pd

from idas_sumo.errors import InputError
from idas_sumo.evaluation.policies import LEARNED_METHODS
from idas_sumo.io_utils import atomic_open, file_digest, read_csv_columns
from idas_sumo.resources import POLICY_DIR, resolve_user_path
from idas_sumo.training.checkpoint import TrainingCheckpoint, load_checkpoint
from idas_sumo.training.metrics import METRICS_NAME

CURVE_WINDOW = 200  # episodes averaged for the end-of-stage numbers
USED_COLUMNS = (
    "stage",
    "episode",
    "global_episode",
    "success",
    "perfect",
    "timed_out",
    "return_mean",
    "wall_time_s",
)
"""The metrics.csv columns read here."""


def stage_summaries(metrics: pd.DataFrame) -> dict[str, dict[str, float]]:
    out = {}
    for stage, rows in metrics.groupby("stage", sort=False):
        tail = rows.tail(CURVE_WINDOW)
        out[str(stage)] = {
            "episodes": int(rows["episode"].max() + 1),
            "last_episodes_averaged": len(tail),
            "success_rate": round(float(tail["success"].mean()), 4),
            "perfect_rate": round(float(tail["perfect"].mean()), 4),
            "timeout_rate": round(float(tail["timed_out"].mean()), 4),
            "mean_return": round(float(tail["return_mean"].mean()), 4),
            "first_episodes_success_rate": round(float(rows.head(CURVE_WINDOW)["success"].mean()), 4),
            "first_episodes_mean_return": round(float(rows.head(CURVE_WINDOW)["return_mean"].mean()), 4),
        }
    return out


def _validation_pick(data: TrainingCheckpoint) -> dict | None:
    """For a ``<stage>_best.pt``: the episode it was saved at and its held-out score."""
    if data.validation is None:
        return None
    return {
        "stage_episode": data.episode,
        "global_episode": data.global_episode,
        "validation_scenarios": data.config.validation_scenarios,
        "validation_seed": data.config.validation_seed,
        **{k: round(float(v), 4) for k, v in dataclasses.asdict(data.validation).items()},
    }


def _validation_curve(path: Path, stages: list[str] | None) -> list[dict] | None:
    """The run's validation.csv rows (greedy policy on the held-out scenarios), when it has one."""
    if not path.exists():
        return None
    rows = pd.read_csv(path)
    if stages:
        rows = rows[rows["stage"].isin(stages)]
    columns = ["stage", "episode", "joint_return", "success_rate", "perfect_rate", "mean_end_time_s"]
    return [
        {k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()}
        for r in rows[columns].to_dict("records")
    ]


def budget_run_record(run_metrics: pd.DataFrame, budget_dir: Path, stages: list[str] | None) -> dict:
    """The larger-budget run of the same seed, after checking that its first rows are ``run_metrics``'s."""
    budget = pd.read_csv(budget_dir / "metrics.csv")
    if stages:
        budget = budget[budget["stage"].isin(stages)]
    own = run_metrics.drop(columns="wall_time_s").reset_index(drop=True)
    prefix = budget.head(len(own)).drop(columns="wall_time_s").reset_index(drop=True)
    if len(budget) < len(own) or not prefix.equals(own):
        raise ValueError(f"{budget_dir}: its first {len(own)} episodes are not the checkpoint run's")
    return {
        "run": str(budget_dir),
        "global_episodes": int(budget["global_episode"].max() + 1),
        "identical_first_episodes": len(own),
        "wall_time_s": round(float(budget["wall_time_s"].max()), 1),
        "stages": stage_summaries(budget),
        "validation_curve": _validation_curve(budget_dir / "validation.csv", stages),
    }


def init_digest(init_from: str) -> str | None:
    """The SHA-256 of the checkpoint the run started from, found as training finds it (tests match it to a
    shipped policy's)."""
    path = resolve_user_path(init_from) if init_from else None
    return file_digest(path) if path is not None and path.is_file() else None


def rl_episodes_text(data: TrainingCheckpoint, start_episodes: int) -> str:
    """What the weights' RL episodes were: the start's, then this run's up to the checkpoint."""
    start = data.config.init_from or "random weights"
    own = f"{data.global_episode:,} episodes of this run (to {data.stage} episode {data.episode:,})"
    return f"{start_episodes:,} of its start ({start}) + {own}"


def recipe_names(command: str) -> list[str]:
    """The file names of the ``--config`` recipes a made-with command trains from (tests check they ship)."""
    words = command.split()
    return [Path(words[i + 1]).name for i, w in enumerate(words[:-1]) if w == "--config"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("name", choices=tuple(LEARNED_METHODS))
    parser.add_argument("--command", required=True, help="the train command that made the run")
    parser.add_argument("--stages", nargs="*", help="only these stages' metrics (default: all in the run)")
    parser.add_argument("--note", default="", help="how the run relates to the paper's budget and recipe")
    parser.add_argument(
        "--start-rl-episodes",
        type=int,
        default=0,
        help="RL episodes the run's start (init_from) had seen: 0 for random weights or an imitation",
    )
    parser.add_argument(
        "--budget-run",
        type=Path,
        help="the same seed's run on a larger budget (its first episodes are this run's)",
    )
    args = parser.parse_args()
    try:  # a damaged checkpoint or metrics file is one line, and nothing in the package is touched
        data = load_checkpoint(args.checkpoint)
        metrics = read_csv_columns(args.checkpoint.parent / METRICS_NAME, USED_COLUMNS, "idas-sumo train")
    except InputError as err:
        print(f"ship_policy: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    if args.stages:
        metrics = metrics[metrics["stage"].isin(args.stages)]
    wall_s = float(metrics["wall_time_s"].max())
    try:
        budget_run = budget_run_record(metrics, args.budget_run, args.stages) if args.budget_run else None
    except (OSError, ValueError, KeyError) as err:
        print(f"ship_policy: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    packages = {p: metadata.version(p) for p in ("idas-sumo", "torch", "eclipse-sumo", "libsumo", "numpy")}
    # The stage sets the central critic (training/curriculum.py): record what the learner ran with, not the
    # recipe's value, which the stage overrides.
    central_critic = bool(data.learner["config"]["use_central_critic"])
    config = data.config.as_dict()
    config["learner"]["use_central_critic"] = central_critic
    meta = {
        "policy": args.name,
        "file": f"{args.name}.pt",
        "file_sha256": file_digest(args.checkpoint),
        "made_with": args.command,
        "recipes": recipe_names(args.command),
        "source_checkpoint": str(args.checkpoint),
        "init_from_sha256": init_digest(data.config.init_from),
        "stage_of_checkpoint": data.stage,
        "run_episodes": int(metrics["global_episode"].max() + 1),
        "checkpoint_global_episode": data.global_episode,
        "central_critic": central_critic,
        "rl_episodes_in_weights": args.start_rl_episodes + data.global_episode,
        "rl_episodes_in_weights_are": rl_episodes_text(data, args.start_rl_episodes),
        "seed": data.config.seed,
        "wall_time_s": round(wall_s, 1),
        "machine": f"{platform.machine()}, {platform.python_version()}, {os.cpu_count()} CPU cores, no GPU",
        "stages": stage_summaries(metrics),
        "picked_by_validation": _validation_pick(data),
        "validation_curve": _validation_curve(args.checkpoint.parent / "validation.csv", args.stages),
        **({"budget_run": budget_run} if budget_run else {}),
        "config": config,
        "packages": {**packages, "python": platform.python_version()},
        "shipped_on": dt.date.today().isoformat(),
        "note": args.note or "See docs/results.md for how this policy was trained.",
    }
    out = POLICY_DIR
    out.mkdir(exist_ok=True)
    # Each file whole or not at all (the shipped policy is read by every default evaluate).
    with atomic_open(out / f"{args.name}.pt", "wb") as f, args.checkpoint.open("rb") as source:
        shutil.copyfileobj(source, f)
    with atomic_open(out / f"{args.name}.json") as f:
        f.write(json.dumps(meta, indent=2, default=str) + "\n")
    print(f"wrote {out / (args.name + '.pt')} and {args.name}.json")


if __name__ == "__main__":
    main()
