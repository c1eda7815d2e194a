"""The equal-terms table (issue 36): every recipe's methods, each training seed's own pick, on declared seeds.

    python scripts/equal_terms.py --recipe ours=runs/ours --recipe paper=runs/paper --out results/equal-terms [--reuse]

Each recipe's runs directory holds its ``picks.csv`` (``scripts/paper_pick.py``): per method and training seed the
run's own validation pick (``<stage>_best.pt``) and whether it is the method's pick. Every such checkpoint, and the
run's weights at the end of its budget (``<stage>.pt``), is evaluated under the paper's protocol (``idas-sumo evaluate --policy``, 100 scenarios per evaluation seed, the
defaults: feasible entries, own-lane mask, every other car on the shipped IDAS), and so are the reference methods
(``warm_start`` and the rules) once per evaluation seed. Writes OUT/episodes.csv (every episode, with its recipe,
method and training seed) and OUT/equal_terms.csv: per method, success and perfect success for each training seed
(over all evaluation seeds' scenarios), their mean and standard deviation over training seeds, the method's pick,
and the paper's figure (Fig. 4, left) where it prints one.
"""

from __future__ import annotations

import argparse
import functools
import json
import subprocess
import sys
from pathlib import Path

import pandas as pd

from idas_sumo.errors import InputError
from idas_sumo.io_utils import (
    atomic_open,
    ensure_writable_dir,
    file_digest,
    read_csv_columns,
    write_csv_atomic,
)
from idas_sumo.resources import POLICY_DIR

EVALUATION_SEEDS = (2031, 2032, 2033)
"""Declared in experiments/diary.md before any run ("Declared: the evaluation seeds for issue 36's ...")."""
REFERENCES = ("warm_start", "idm", "fsm_idm", "fsm_idm_smooth")
PAPER_FIGURES: dict[str, tuple[float, float]] = {
    "idas": (100.0, 95.0),
    "idas_v": (93.0, 64.0),
    "idas_direct": (77.0, 23.0),
    "idm": (80.0, 12.0),
    "fsm_idm": (94.0, 57.0),
}
"""The paper's success and perfect success, % (its Fig. 4 table), by the method it names."""
PICK_COLUMNS = ("method", "seed", "checkpoint", "picked", "best_episode")
EPISODE_COLUMNS = ("scenario", "seed", "success", "perfect")
INPUTS_NAME = "equal_terms_inputs.json"
"""Beside each evaluation's CSVs: what it was run from, so that ``--reuse`` can skip it when nothing changed."""


def evaluation_inputs(command: list[str], policy: Path | None) -> dict[str, object]:
    """What an evaluation's episodes depend on besides the code: its command, the checkpoint it evaluates and
    every shipped policy (the other cars drive the shipped IDAS; references load their own)."""
    return {
        "command": command,
        "policy_sha256": file_digest(policy) if policy is not None else None,
        "shipped_policies_sha256": _shipped_digests(),
    }


@functools.cache
def _shipped_digests() -> dict[str, str]:
    """The shipped policies' digests, read once per run (they do not change while it evaluates)."""
    return {p.name: file_digest(p) for p in sorted(POLICY_DIR.glob("*.pt"))}


def evaluate(
    method: str, policy: Path | None, seed: int, out: Path, scenarios: int, reuse: bool = False
) -> pd.DataFrame:
    """One ``idas-sumo evaluate`` run, its episodes.csv read back. ``reuse``: an earlier run into ``out`` from
    the same inputs is read back instead (it trusts that evaluation's code has not changed since)."""
    command = [
        "idas-sumo",
        "evaluate",
        "--baseline",
        method,
        "--scenarios",
        str(scenarios),
        "--seed",
        str(seed),
    ]
    if policy is not None:
        command += ["--policy", str(policy)]
    command += ["--out", str(out), "--force", "--no-progress"]
    inputs = evaluation_inputs(command, policy)
    marker = out / INPUTS_NAME
    episodes_csv = out / "episodes.csv"
    if reuse and episodes_csv.is_file() and marker.is_file() and json.loads(marker.read_text()) == inputs:
        return read_csv_columns(episodes_csv, EPISODE_COLUMNS, "idas-sumo evaluate")
    marker.unlink(missing_ok=True)  # (a failed run leaves no marker to trust)
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise InputError(f"{' '.join(command)}: {done.stderr.strip().splitlines()[-1:]}")
    with atomic_open(marker, "w") as f:
        json.dump(inputs, f, indent=1)
    return read_csv_columns(episodes_csv, EPISODE_COLUMNS, "idas-sumo evaluate")


def base_method(method: str, suffix: str) -> str:
    """The learned method a recipe's pick is evaluated as (idas_v_paper -> idas_v)."""
    return method[: -len(suffix)] if suffix and method.endswith(suffix) else method


def recipe_episodes(
    name: str, root: Path, seeds: list[int], out: Path, scenarios: int, reuse: bool = False
) -> pd.DataFrame:
    """Every training seed's pick of every method of one recipe, on every evaluation seed."""
    picks = read_csv_columns(root / "picks.csv", PICK_COLUMNS, "scripts/paper_pick.py")
    suffix = "" if name == "ours" else f"_{name}"
    frames = []
    for row in picks.itertuples():
        base = base_method(str(row.method), suffix)
        best = Path(str(row.checkpoint))
        # The run's own pick, and the weights at the end of its budget (<stage>.pt beside <stage>_best.pt).
        for weights, path in (("pick", best), ("last", best.with_name(best.name.replace("_best", "")))):
            for seed in seeds:
                where = out / "runs" / str(row.method) / f"train{row.seed}-{weights}" / f"eval{seed}"
                episodes = evaluate(base, path, seed, where, scenarios, reuse)
                episodes["recipe"], episodes["method"], episodes["base"] = name, row.method, base
                episodes["weights"], episodes["training_seed"] = weights, int(row.seed)
                episodes["picked"] = bool(row.picked) and weights == "pick"
                episodes["pick_episode"] = int(row.best_episode) if weights == "pick" else -1
                frames.append(episodes)
    return pd.concat(frames, ignore_index=True)


def reference_episodes(seeds: list[int], out: Path, scenarios: int, reuse: bool = False) -> pd.DataFrame:
    frames = []
    for method in REFERENCES:
        for seed in seeds:
            episodes = evaluate(method, None, seed, out / "runs" / method / f"eval{seed}", scenarios, reuse)
            episodes["recipe"], episodes["method"], episodes["base"] = "reference", method, method
            episodes["weights"], episodes["training_seed"] = "pick", -1
            episodes["picked"], episodes["pick_episode"] = True, -1
            frames.append(episodes)
    return pd.concat(frames, ignore_index=True)


def pick_columns(pick: pd.DataFrame) -> dict[str, object]:
    """The method's pick on the evaluation seeds (none for the weights at the end of the budget)."""
    if pick.empty:
        return {"pick_training_seed": None, "pick_episode": None, "pick_success": None, "pick_perfect": None}
    return {
        "pick_training_seed": int(pick["training_seed"].iloc[0]),
        "pick_episode": int(pick["pick_episode"].iloc[0]),
        "pick_success": round(100.0 * float(pick["success"].mean()), 2),
        "pick_perfect": round(100.0 * float(pick["perfect"].mean()), 2),
    }


def summary(episodes: pd.DataFrame) -> pd.DataFrame:
    """One row per method and weights (each run's pick, or its last): per training seed, mean ± sd over training
    seeds, the method's pick, the paper's figure."""
    rows = []
    keys = ["recipe", "method", "weights"]
    for (recipe, method, weights), group in episodes.groupby(keys, sort=False):
        per_seed = group.groupby("training_seed")[["success", "perfect"]].mean() * 100.0
        pick = group[group["picked"]]
        paper = PAPER_FIGURES.get(str(group["base"].iloc[0]), (float("nan"), float("nan")))
        rows.append(
            {
                "recipe": recipe,
                "method": method,
                "weights": weights,
                "training_seeds": len(per_seed),
                "scenarios_per_seed": int(len(group) / len(per_seed)),
                "success_per_seed": " / ".join(f"{v:.1f}" for v in per_seed["success"]),
                "perfect_per_seed": " / ".join(f"{v:.1f}" for v in per_seed["perfect"]),
                "success_mean": round(float(per_seed["success"].mean()), 2),
                "success_sd": round(float(per_seed["success"].std(ddof=1)), 2) if len(per_seed) > 1 else None,
                "perfect_mean": round(float(per_seed["perfect"].mean()), 2),
                "perfect_sd": round(float(per_seed["perfect"].std(ddof=1)), 2) if len(per_seed) > 1 else None,
                **pick_columns(pick),
                "paper_success": paper[0],
                "paper_perfect": paper[1],
            }
        )
    return pd.DataFrame(rows)


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--recipe",
        action="append",
        default=[],
        metavar="NAME=DIR",
        help="a recipe's runs (its picks.csv); NAME 'ours' ships without a suffix, any other as _NAME",
    )
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=list(EVALUATION_SEEDS))
    parser.add_argument("--scenarios", type=int, default=100)
    parser.add_argument(
        "--reuse",
        action="store_true",
        help="read back an evaluation already in OUT whose command, checkpoint and shipped policies are the same "
        "(after adding a training seed, only its checkpoints are evaluated)",
    )
    args = parser.parse_args()
    try:
        recipes = [tuple(item.split("=", 1)) for item in args.recipe]
        if not recipes or any(len(r) != 2 for r in recipes):
            raise InputError("--recipe NAME=DIR, at least one (e.g. --recipe ours=runs/ours)")
        ensure_writable_dir(args.out)
        frames = [
            recipe_episodes(n, Path(d), args.seeds, args.out, args.scenarios, args.reuse) for n, d in recipes
        ]
        episodes = pd.concat([*frames, reference_episodes(args.seeds, args.out, args.scenarios, args.reuse)])
    except InputError as err:
        print(f"equal_terms: {err}", file=sys.stderr)
        return 2
    write_csv_atomic(episodes, args.out / "episodes.csv")
    table = summary(episodes)
    write_csv_atomic(table, args.out / "equal_terms.csv")
    with pd.option_context("display.width", 250, "display.max_columns", 30):
        print(table.to_string(index=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
