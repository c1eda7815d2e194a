"""``idas-sumo sweep``: whole training runs over seeds and config values, and one table of their results.

The runs are the cartesian product of ``--seeds`` and each ``--set key=v1,v2`` (keys as in the training
TOML, nested ones with dots: ``learner.gamma``). Each run is an ordinary run directory under ``--out``,
so an interrupted sweep picks up where it stopped: a run with a ``checkpoint.pt`` resumes, a finished
one only reads its results. Without ``--ray-address`` the runs go one after another in this process;
with it each run is a Ray task on the cluster, reserving the run's ``workers`` CPUs (its rollout
workers are processes on the node the task lands on).

The table (``sweep.csv``, and ``sweep.png``) has one row per run: its seed and set values, the best
validation of its last stage (``<stage>_best.pt``, so the config must validate: ``validate_every`` >
0), and with ``--evaluate`` that checkpoint's evaluation on the paper suite with a declared seed (the
``evaluate`` function the command line passes in: evaluation/best_checkpoint.py, a module this layer
does not import).
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import math
import re
import tomllib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeAlias

from idas_sumo.config import load_toml
from idas_sumo.errors import InputError
from idas_sumo.sim.merge_detect import MergeSite, choose_merge
from idas_sumo.sim.processes import SEED_LIMIT
from idas_sumo.training.config import RESUME_FIELDS, TrainConfig, load_train_config, train_config_from_dict

__all__ = [
    "SWEEP_CSV",
    "SWEEP_PNG",
    "Evaluate",
    "SweepRun",
    "parse_seeds",
    "parse_sets",
    "plan_sweep",
    "run_sweep",
]

SWEEP_CSV = "sweep.csv"
SWEEP_PNG = "sweep.png"
EVAL_DIR = "evaluation"
"""A run's evaluation of its best checkpoint, inside its run directory."""
MAX_RUNS = 10_000
"""More runs than this is a typo (a seed range such as 0-1000000), not a sweep."""


@dataclasses.dataclass(frozen=True)
class SweepRun:
    """One run of the sweep: its name (its folder under ``--out``), seed, set values and config."""

    name: str
    seed: int
    values: tuple[tuple[str, Any], ...]
    config: TrainConfig


Evaluate: TypeAlias = Callable[[Path, MergeSite, Path], dict[str, Any]]
"""``evaluate(best checkpoint, the run's merge site, output folder)``: columns for the run's row. It runs where the run
ran (a Ray task on the cluster): a module-level function, or a ``functools.partial`` of one."""


def parse_seeds(text: str) -> list[int]:
    """``0-4`` (inclusive), ``0,3,7``, or a mix (``0-2,9``); an ``InputError`` for anything else."""
    seeds: list[int] = []
    for part in text.split(","):
        m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", part)
        if m is None:
            raise InputError(f"--seeds: expected seeds such as 0-4 or 0,3,7, got {text!r}")
        lo, hi = int(m.group(1)), int(m.group(2) or m.group(1))
        if hi < lo:
            raise InputError(f"--seeds: the range {part.strip()!r} runs backwards")
        if hi >= SEED_LIMIT:  # as train --seed: checked here, not by SUMO after the folder was made
            raise InputError(f"--seeds: seed {hi} is outside [0, {SEED_LIMIT}) (SUMO's seed range)")
        if hi - lo + len(seeds) >= MAX_RUNS:
            raise InputError(f"--seeds: more than {MAX_RUNS} seeds in {text!r}")
        seeds.extend(range(lo, hi + 1))
    if len(set(seeds)) != len(seeds):
        raise InputError(f"--seeds: a seed appears twice in {text!r}")
    return seeds


def _value(text: str) -> Any:
    """A ``--set`` value as TOML reads it (0.9, 4, true, "x"); a bare word is a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def parse_sets(items: Sequence[str]) -> list[tuple[str, list[Any]]]:
    """``["learner.gamma=0.9,0.99", "stage=robot"]`` -> ``[("learner.gamma", [0.9, 0.99]), ("stage", ["robot"])]``."""
    sets: list[tuple[str, list[Any]]] = []
    for item in items:
        key, sep, values = item.partition("=")
        key = key.strip()
        if not sep or not key or not values.strip():
            raise InputError(f"--set: expected KEY=V1,V2,..., got {item!r}")
        if key == "seed":
            raise InputError("--set seed: give the seeds with --seeds")
        if key in (k for k, _ in sets):
            raise InputError(f"--set {key}: given twice (list its values in one --set)")
        parsed = [_value(v.strip()) for v in values.split(",")]
        if len({repr(v) for v in parsed}) != len(parsed):
            raise InputError(f"--set {key}: a value appears twice in {values!r}")
        sets.append((key, parsed))
    return sets


def _with_value(data: dict[str, Any], key: str, value: Any) -> None:
    """Set dotted ``key`` in the TOML table ``data`` (``learner.gamma``: table ``learner``, key ``gamma``)."""
    *tables, last = key.split(".")
    table = data
    for i, name in enumerate(tables):
        inner = table.setdefault(name, {})
        if not isinstance(inner, dict):
            raise InputError(f"--set {key}: {'.'.join(tables[: i + 1])} is a value, not a table")
        table = inner
    table[last] = value


def _slug(value: Any) -> str:
    """A value as it can stand in a folder name."""
    return re.sub(r"[^A-Za-z0-9.+-]+", "_", str(value)).strip("_") or "_"


def plan_sweep(
    config_path: Path, seeds: Sequence[int], sets: Sequence[tuple[str, list[Any]]]
) -> list[SweepRun]:
    """Every run of the sweep, each config checked as the training TOML is (a bad key or value is an
    ``InputError`` naming it, with a did-you-mean for a misspelt key)."""
    load_train_config(config_path)  # the file's own mistakes are named as the file's
    for seed in seeds:
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < SEED_LIMIT:
            raise InputError(f"seeds: {seed!r} is not an integer in [0, {SEED_LIMIT}) (SUMO's seed range)")
    base = load_toml(config_path)
    combos = list(itertools.product(*(values for _, values in sets)))
    if len(seeds) * len(combos) > MAX_RUNS:
        raise InputError(f"the sweep has {len(seeds) * len(combos)} runs, more than {MAX_RUNS}")
    runs = []
    for combo in combos:
        values = tuple((key, v) for (key, _), v in zip(sets, combo, strict=True))
        data = copy.deepcopy(base)
        for key, v in values:
            _with_value(data, key, v)
        for seed in seeds:
            data["seed"] = seed
            config = train_config_from_dict(data, "--set")
            if config.validate_every == 0:
                raise InputError(
                    f"{config_path}: validate_every = 0; a sweep ranks runs by their best validation "
                    "(set validate_every in the file or with --set validate_every=N)"
                )
            name = "_".join([f"seed-{seed}", *(f"{key}-{_slug(v)}" for key, v in values)])
            runs.append(SweepRun(name, seed, values, config))
    return runs


def check_earlier_run(run: SweepRun, run_dir: Path) -> None:
    """Refuse a run folder an earlier sweep left that was trained with another config than ``run``'s (the
    sweep's TOML changed since): it would be reused, or resumed, as if it were this sweep's run. The fields
    ``train --resume`` takes from a new config (workers, copies, episode budgets) may differ."""
    from idas_sumo.training.checkpoint import load_checkpoint
    from idas_sumo.training.curriculum import plan_stages
    from idas_sumo.training.loop import CHECKPOINT_NAME

    stage = plan_stages(run.config)[-1].name
    earlier = [p for p in (run_dir / f"{stage}.pt", run_dir / CHECKPOINT_NAME) if p.is_file()]
    if not earlier:
        return
    saved = load_checkpoint(earlier[0]).config
    differ = [
        f.name
        for f in dataclasses.fields(TrainConfig)
        if f.name not in RESUME_FIELDS and getattr(saved, f.name) != getattr(run.config, f.name)
    ]
    if differ:
        raise InputError(
            f"{run_dir}: trained by an earlier sweep with another config ({', '.join(differ)} differ from "
            "this sweep's); move it away or sweep into another --out"
        )


def _run_one(job: tuple[SweepRun, MergeSite, Path, Evaluate | None]) -> dict[str, Any]:
    """Train one run (resuming it when its folder holds a checkpoint), optionally evaluate its best
    checkpoint; its table row. What a Ray task runs, and the local loop too."""
    from idas_sumo.training.curriculum import plan_stages
    from idas_sumo.training.loop import CHECKPOINT_NAME, run_training

    run, net, out, evaluate = job
    run_dir = out / run.name
    stage = plan_stages(run.config)[-1].name
    best = run_dir / f"{stage}_best.pt"
    if not (run_dir / f"{stage}.pt").is_file() or not best.is_file():
        resume = (run_dir / CHECKPOINT_NAME).is_file()
        run_training(net, run.config, run_dir, resume=resume, progress=False)
    return _row(run, run_dir, stage, best, net, evaluate)


def _row(
    run: SweepRun, run_dir: Path, stage: str, best: Path, net: MergeSite, evaluate: Evaluate | None
) -> dict[str, Any]:
    from idas_sumo.training.checkpoint import load_checkpoint

    saved = load_checkpoint(best)
    score = saved.validation
    row: dict[str, Any] = {"run": run.name, "seed": run.seed, **dict(run.values), "stage": stage}
    row.update(
        best_episode=saved.episode,
        best_joint_return=score.joint_return if score else math.nan,
        best_success_rate=score.success_rate if score else math.nan,
        best_perfect_rate=score.perfect_rate if score else math.nan,
    )
    if evaluate is not None:
        row.update(evaluate(best, net, run_dir / EVAL_DIR))
    row["run_dir"] = str(run_dir)
    return row


def run_sweep(
    config_path: Path,
    net: Path,
    seeds: Sequence[int],
    sets: Sequence[tuple[str, list[Any]]],
    out: Path,
    ray_address: str | None = None,
    evaluate: Evaluate | None = None,
    on_run: Callable[[dict[str, Any]], None] | None = None,
) -> tuple[Path, Path]:
    """Run (or resume) every run of the sweep, then write its table; returns (sweep.csv, sweep.png).
    ``evaluate``: also evaluate each run's best checkpoint (see ``Evaluate``). ``on_run(row)`` as each
    run finishes."""
    import pandas as pd

    from idas_sumo.io_utils import ensure_writable_dir, write_csv_atomic

    runs = plan_sweep(config_path, seeds, sets)
    if not net.is_file():
        raise InputError(f"{net}: network file not found")
    # Each merge the runs train on, parsed once here; its path absolute: a Ray task may run in another
    # working directory (or on another node).
    sites = {j: choose_merge(net.resolve(), j) for j in {run.config.env.junction for run in runs}}
    for run in runs:
        check_earlier_run(run, out / run.name)
    ensure_writable_dir(out)  # only once every check passed: a refused sweep leaves no folder behind
    jobs = [(run, sites[run.config.env.junction], out.resolve(), evaluate) for run in runs]
    if ray_address is None:
        rows = []
        for job in jobs:
            rows.append(_run_one(job))
            if on_run is not None:
                on_run(rows[-1])
    else:
        from idas_sumo.distributed.ray_pool import map_tasks, ray_session

        cpus = max(run.config.rollout_workers() for run in runs)
        done = None if on_run is None else (lambda i, row: on_run(row))
        with ray_session(ray_address, num_cpus=max(cpus, _local_cpus())):
            rows = map_tasks(_run_one, jobs, num_cpus=cpus, on_done=done)
    table = pd.DataFrame(rows)
    csv_path, png_path = out / SWEEP_CSV, out / SWEEP_PNG
    write_csv_atomic(table, csv_path)
    _plot(table, png_path)
    return csv_path, png_path


def _local_cpus() -> int:
    from idas_sumo.sim.processes import max_workers

    return max_workers()


def _plot(table: Any, path: Path) -> None:
    """One bar per run: its best validation joint return (and its evaluation success, if any)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from idas_sumo.io_utils import atomic_open

    evaluated = "eval_success_pct" in table.columns
    seed = f" (seed {int(table['eval_seed'].iloc[0])})" if "eval_seed" in table.columns else ""
    fig, axes = plt.subplots(
        1, 2 if evaluated else 1, figsize=(max(4.0, 0.6 * len(table)) * (2 if evaluated else 1), 4)
    )
    axes = list(axes) if evaluated else [axes]
    axes[0].bar(table["run"], table["best_joint_return"], color="tab:blue")
    axes[0].set_ylabel("best validation joint return")
    if evaluated:
        axes[1].bar(table["run"], table["eval_success_pct"], color="tab:green")
        axes[1].set_ylabel(f"evaluation success %{seed}")
    for ax in axes:
        ax.tick_params(axis="x", labelrotation=60, labelsize=7)
    fig.tight_layout()
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=100)
    plt.close(fig)
