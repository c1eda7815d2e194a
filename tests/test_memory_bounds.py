"""No input exhausts the machine (issue 34): an evaluation keeps a CSV row per episode, not its trajectory;
every count a user gives is bounded by the one ``MAX_SCENARIOS``; a cached net is checked again before
SUMO reads it."""

from __future__ import annotations

import gc
import os
import re
import weakref
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import pandas as pd
import pytest
from conftest import run_cli

from idas_sumo.cli import common as cli_common
from idas_sumo.cli import main
from idas_sumo.config import MAX_SCENARIOS
from idas_sumo.errors import InputError
from idas_sumo.evaluation import runner
from idas_sumo.evaluation.metrics import TRAJECTORY_COLUMNS
from idas_sumo.evaluation.protocol import EpisodeResult, EvalJob, suite_cases
from idas_sumo.evaluation.runner import EvalRequest, run_evaluation
from idas_sumo.io_utils import file_digest
from idas_sumo.sim import multinet
from idas_sumo.sim.multinet import CACHE_ENV_VAR, sumo_load_problem
from idas_sumo.sim.net_cache import cached_net
from idas_sumo.sim.netgen import NetParams, read_merge_net
from idas_sumo.training.config import ConfigValueError, TrainConfig


def _trajectory(scenario: int, rows: int) -> pd.DataFrame:
    return pd.DataFrame(
        [
            (float(t), f"v{t % 3}", True, "idm", "main", 10.5 - t, 5.0 + t / 7, -0.25, -1, "1111111")
            for t in range(rows)
        ],
        columns=list(TRAJECTORY_COLUMNS),
    ).assign(time_s=lambda f: f["time_s"] + scenario)


class _NoEngine:
    """Stands in for MergeEngine: the fake ``run_jobs`` below runs no SUMO."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        pass

    def close(self) -> None:
        pass


def _fake_runs(alive: list[weakref.ref[pd.DataFrame]], held: list[int]) -> Any:
    """A ``run_jobs`` whose results carry trajectories it watches: before yielding each, it counts how
    many of the trajectories yielded before are still alive (held by the evaluation)."""

    def run_jobs(
        engine: object, jobs: Sequence[EvalJob], *args: object
    ) -> Iterator[tuple[EvalJob, EpisodeResult]]:
        for i, job in enumerate(jobs):
            gc.collect()
            held.append(sum(r() is not None for r in alive))
            trajectory = _trajectory(i, 40)
            alive.append(weakref.ref(trajectory))
            episode = {"scenario": job.case.scenario.name, "method": job.method, "success": 1, "perfect": 1}
            yield job, EpisodeResult(episode, {"scenario": job.case.scenario.name}, trajectory)

    return run_jobs


@pytest.mark.parametrize("trajectories", [False, True])
def test_evaluation_keeps_no_trajectory_once_its_rows_are_taken(
    tmp_path: Path, net_path: Path, monkeypatch: pytest.MonkeyPatch, trajectories: bool
) -> None:
    """Before: every result (with its trajectory) was kept until the last episode ended, about 0.2 MB
    per scenario; now each is dropped (or streamed to trajectories.csv) as soon as it is read."""
    alive: list[weakref.ref[pd.DataFrame]] = []
    held: list[int] = []
    monkeypatch.setattr(runner, "MergeEngine", _NoEngine)
    monkeypatch.setattr(runner, "run_jobs", _fake_runs(alive, held))
    out = tmp_path / "out"
    run_evaluation(
        EvalRequest(
            net=net_path,
            methods=("idm",),
            others="idm",
            scenarios=12,
            out=out,
            progress=False,
            trajectories=trajectories,
        )
    )
    assert len(held) == 12
    assert max(held) <= 1, held  # at most the one just yielded is still being read
    if trajectories:
        written = (out / "trajectories.csv").read_text()
        expected = pd.concat(
            [_trajectory(i, 40).assign(scenario=f"paper-{i:03d}", run_method="idm") for i in range(12)],
            ignore_index=True,
        )[["scenario", "run_method", *TRAJECTORY_COLUMNS]].to_csv(index=False, lineterminator="\n", na_rep="")
        assert written == expected  # one episode at a time: the bytes of one frame of them all
    else:
        assert not (out / "trajectories.csv").exists()


# --- one bound for every count ---------------------------------------------------------------------


def test_the_command_line_bound_is_the_one_bound() -> None:
    assert cli_common.MAX_SCENARIOS is MAX_SCENARIOS
    assert cli_common.scenario_count(str(MAX_SCENARIOS)) == MAX_SCENARIOS


def test_validation_scenarios_is_bounded_like_scenarios() -> None:
    assert TrainConfig(validation_scenarios=MAX_SCENARIOS).validation_scenarios == MAX_SCENARIOS
    with pytest.raises(ConfigValueError, match=f"validation_scenarios must be at most {MAX_SCENARIOS}"):
        TrainConfig(validation_scenarios=50_000_000)


def test_train_refuses_a_recipe_with_too_many_validation_scenarios(
    tmp_path: Path, net_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before: accepted, and the held-out scenarios were drawn up front (about 15 MB/s)."""
    recipe = tmp_path / "big.toml"
    recipe.write_text("validate_every = 16\nvalidation_scenarios = 50000000\n")
    out = tmp_path / "run"
    code = main(
        ["train", "--net", str(net_path), "--config", str(recipe), "--episodes", "1", "--out", str(out)]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    (line,) = err.splitlines()
    assert "validation_scenarios" in line and str(MAX_SCENARIOS) in line and str(recipe) in line
    assert not out.exists()


def test_the_python_api_bounds_scenarios_as_the_command_line_does(tmp_path: Path, net_path: Path) -> None:
    with pytest.raises(InputError, match=f"at most {MAX_SCENARIOS}"):
        suite_cases("paper", MAX_SCENARIOS + 1, 0, {"main": 20.0, "merge": 15.0}, _traffic())
    out = tmp_path / "out"
    with pytest.raises(InputError, match=f"at most {MAX_SCENARIOS}"):
        run_evaluation(
            EvalRequest(
                net=net_path, methods=("idm",), others="idm", scenarios=10**9, out=out, progress=False
            )
        )
    assert not out.exists()


def _traffic() -> Any:
    from idas_sumo.env.scenario import TrafficConfig

    return TrafficConfig()


# --- a cached net is checked again before SUMO reads it ---------------------------------------------


def _tamper(net: Path) -> None:
    """Empty every shape (SUMO segfaults loading it) and write the matching digest beside it."""
    text = re.sub(r'shape="[^"]*"', 'shape=""', net.read_text())
    net.write_text(text)
    net.with_name(net.name + ".sha256").write_text(file_digest(net) + "\n")


def test_a_tampered_cached_net_with_its_digest_is_rebuilt_before_sumo_reads_it(
    tmp_path: Path, net_path: Path
) -> None:
    """Before: the edited multi-copy net passed the digest check and SUMO crashed (rc -11, no message)."""
    env = {**os.environ, CACHE_ENV_VAR: str(tmp_path / "cache"), "PYTHONUNBUFFERED": "1"}
    args = ["evaluate", "--baseline", "idm", "--others", "idm", "--scenarios", "2", "--copies", "2"]
    args += ["--net", str(net_path), "--no-progress"]
    first = run_cli(*args, "--out", str(tmp_path / "first"), env=env)
    assert first.returncode == 0, first.stderr
    (cached,) = (tmp_path / "cache").glob("*-k2.net.xml")
    _tamper(cached)
    assert sumo_load_problem(cached) == "SUMO crashed loading it (signal 11)"
    again = run_cli(*args, "--out", str(tmp_path / "again"), env=env)
    assert again.returncode == 0, again.stderr
    assert "the cached net fails its check (SUMO crashed loading it" in again.stderr
    assert sumo_load_problem(cached) is None  # built again
    for name in ("episodes.csv", "flow.csv"):
        assert (tmp_path / "again" / name).read_bytes() == (tmp_path / "first" / name).read_bytes()


def test_a_tampered_generated_net_is_rebuilt_and_a_good_one_checked_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    loads: list[Path] = []

    def counted(path: Path) -> str | None:
        loads.append(path)
        return sumo_load_problem(path)

    monkeypatch.setattr(multinet, "_CHECKED", set())
    monkeypatch.setattr(multinet, "sumo_load_problem", counted)
    params = NetParams(main_length_m=180.0)
    path = cached_net(params, tmp_path)
    assert loads == []  # just built and checked: trusted in this process
    multinet._CHECKED.clear()
    assert cached_net(params, tmp_path) == path and cached_net(params, tmp_path) == path
    assert loads == [path]  # checked once per process
    _tamper(path)
    multinet._CHECKED.clear()
    assert cached_net(params, tmp_path) == path
    assert loads[-1] == path and sumo_load_problem(path) is None  # rebuilt: loads again
    assert read_merge_net(path).main.length_m > 0


def test_validation_merges_are_bounded_by_the_validation_scenarios() -> None:
    """Before: 10^6 validation merges were accepted, each a net built (netconvert) up front. Now at most
    one per validation scenario, and at most MAX_VALIDATION_GEOMETRIES whatever the scenarios."""
    from idas_sumo.training.geometry import MAX_VALIDATION_GEOMETRIES, GeometryConfig, GeometryRangeError

    ok = TrainConfig(validation_scenarios=8, geometry=GeometryConfig(validation_geometries=8))
    assert ok.geometry is not None and ok.geometry.validation_geometries == 8
    with pytest.raises(ConfigValueError, match=r"validation_geometries \(500\) must be at most"):
        TrainConfig(validation_scenarios=40, geometry=GeometryConfig(validation_geometries=500))
    with pytest.raises(GeometryRangeError, match=r"validation_geometries must be in \[0, 1000\]"):
        GeometryConfig(validation_geometries=MAX_VALIDATION_GEOMETRIES + 1)
