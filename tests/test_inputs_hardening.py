"""Issue 34's tracebacks and misleading messages in the less-travelled commands, and their siblings: every
file a command reads back (replay records, plots' CSVs) is checked with one line naming the file and the key
or column; the Python API's arguments are checked as the CLI's are; a step after the episode says to reset;
a refused command leaves nothing behind."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any

import pytest
from conftest import main_in_process

from idas_sumo.env.config import EnvConfig
from idas_sumo.errors import InputError
from idas_sumo.resources import DEFAULT_NET, SCENARIO_DIR
from idas_sumo.sim.processes import SEED_LIMIT

REPLAY_BASE = Path(__file__).parent / "data" / "replay_base"
"""A stored evaluation (IDM among IDM others, two scenarios): its replay needs no policy file."""


def one_line(code: int, err: str, *needles: str) -> None:
    """Exit 2 and one line on stderr holding ``needles``, no traceback."""
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, (code, err)
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


@pytest.fixture
def evaluated(tmp_path: Path) -> Path:
    out = tmp_path / "ev"
    shutil.copytree(REPLAY_BASE, out)
    return out


def edit_json(path: Path, change: Any) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def edit_jsonl(path: Path, change: Any) -> None:
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    change(lines[0])
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))


# -- replay: the run record checked whole, when read -----------------------------------------------


def _set(key: str, value: Any) -> Any:
    return lambda d: d.__setitem__(key, value)


@pytest.mark.parametrize(
    ("change", "needles"),
    [
        # A tiny max_episode_s ran the episode into a ZeroDivisionError; now as evaluate says it.
        (_set("max_episode_s", 0.001), ("run.json: max_episode_s = 0.001 s is shorter",)),
        (_set("max_episode_s", [1]), ("run.json.max_episode_s: expected a number",)),  # was an AttributeError
        (_set("max_episode_s", -3.0), ("run.json", "max_episode_s must be positive")),
        # A bad seed was blamed on scenarios.jsonl (or on the net, by SUMO).
        (_set("seed", "x"), ("run.json.seed: expected an integer",)),
        (_set("seed", -5), ("run.json.seed: must be in [0, 2147483648)",)),
        (_set("seed", 2**40), ("run.json.seed: must be in [0",)),
        (_set("methods", []), ("run.json.methods: expected a table",)),  # was an AttributeError
        (_set("methods", {}), ("run.json.methods: expected a table",)),  # was an IndexError
        (_set("others", 5), ("run.json.others: expected a table",)),
        (
            lambda d: d["others"].__setitem__("path", "/x.pt"),
            ("run.json.others: a rule-based method has no",),
        ),
        (lambda d: d["methods"]["idm"].__setitem__("method", "idas"), ("run.json.methods.idm.method",)),
        (_set("safety_mask", "zz"), ("run.json.safety_mask: 'zz' is not one of",)),
        (_set("junction", 5), ("run.json.junction: expected a string",)),
        (_set("extra", 1), ("run.json: unknown key 'extra'",)),
    ],
)
def test_an_edited_run_record_is_one_line_naming_the_key(
    evaluated: Path, capsys: pytest.CaptureFixture[str], change: Any, needles: tuple[str, ...]
) -> None:
    edit_json(evaluated / "replay" / "run.json", change)
    code, _, err = main_in_process(capsys, "replay", str(evaluated), "--scenario", "0")
    one_line(code, err, *needles)
    assert "scenarios.jsonl" not in err


def _vehicle(key: str, value: Any) -> Any:
    return lambda line: line["vehicles"][0].__setitem__(key, value)


@pytest.mark.parametrize(
    ("change", "needles"),
    [
        (_set("seed", "x"), ("scenarios.jsonl:1.seed: expected an integer",)),
        (_set("seed", -1), ("scenarios.jsonl:1.seed: must be in [0",)),
        (_set("ego", "nobody"), ("scenarios.jsonl:1: ego and method_vehicles",)),
        (_set("vehicles", 5), ("scenarios.jsonl:1.vehicles: expected a list",)),
        (_vehicle("speed_mps", -1.0), ("scenarios.jsonl:1.vehicles[0]", "negative speed_mps")),
        (_vehicle("road", "sky"), ("scenarios.jsonl:1.vehicles[0].road",)),
        (_set("main_prio", 7), ("scenarios.jsonl:1", "main_prio must be 0 or 1")),
    ],
)
def test_an_edited_scenario_line_is_one_line_naming_line_and_key(
    evaluated: Path, capsys: pytest.CaptureFixture[str], change: Any, needles: tuple[str, ...]
) -> None:
    edit_jsonl(evaluated / "replay" / "scenarios.jsonl", change)
    code, _, err = main_in_process(capsys, "replay", str(evaluated), "--scenario", "0")
    one_line(code, err, *needles)


def test_replay_data_that_is_not_json(evaluated: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (evaluated / "replay" / "run.json").write_text("[" * 100_000)
    code, _, err = main_in_process(capsys, "replay", str(evaluated), "--scenario", "0")
    one_line(code, err, "run.json")


def test_replay_out_into_a_folder_it_cannot_write_is_refused_before_the_episode(
    evaluated: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """It ran the whole episode, then failed on three lines. Root may write anywhere, so the folder's
    refusal is simulated where the check meets the file system."""
    import idas_sumo.evaluation.replay as replay

    def refused(*args: Any, **kwargs: Any) -> str:
        raise PermissionError(13, "Permission denied")

    def never(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the episode ran before the output path was checked")

    monkeypatch.setattr(replay.tempfile, "mkdtemp", refused)
    monkeypatch.setattr(replay, "replay_episode", never)
    target = tmp_path / "ro" / "x.gif"
    target.parent.mkdir()
    code, out, err = main_in_process(
        capsys, "replay", str(evaluated), "--scenario", "0", "--out", str(target)
    )
    one_line(code, err, f"--out {target}: cannot write into", "Permission denied")
    assert out == "" and list(target.parent.iterdir()) == []


# -- plot: the CSVs it reads hold numbers where they must ---------------------------------------------


@pytest.mark.parametrize(
    ("name", "column", "row"),
    [("episodes.csv", "perfect", 1), ("episodes.csv", "ego_type", 2), ("flow.csv", "vehicles", 1)],
)
def test_plot_on_text_in_a_numeric_column_names_file_column_and_row(
    evaluated: Path, capsys: pytest.CaptureFixture[str], name: str, column: str, row: int
) -> None:
    import pandas as pd

    path = evaluated / name
    frame = pd.read_csv(path, dtype=str, keep_default_na=False)
    frame.loc[row - 1, column] = "zz"
    frame.to_csv(path, index=False)
    code, _, err = main_in_process(capsys, "plot", str(evaluated))
    one_line(code, err, f"{path}: column {column!r} holds 'zz' in row {row}, expected a number")
    if name == "episodes.csv":  # read first: nothing drawn
        assert not list(evaluated.glob("*.png"))


def test_plot_still_draws_the_untouched_evaluation(
    evaluated: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = main_in_process(capsys, "plot", str(evaluated))
    assert code == 0, err
    assert (evaluated / "summary.png").is_file() and "wrote" in out


@pytest.mark.parametrize("name", ["metrics.csv", "validation.csv"])
def test_plot_on_a_training_csv_with_text_in_a_numeric_column(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    from idas_sumo.training.plots import METRICS_NEEDED
    from idas_sumo.training.validation import VALIDATION_COLUMNS

    columns = METRICS_NEEDED if name == "metrics.csv" else VALIDATION_COLUMNS
    rows = [["direct", *(["1"] * (len(columns) - 1))], ["direct", *(["2"] * (len(columns) - 1))]]
    rows[1][2] = "oops"  # global_episode or return_mean: numbers the curves compute with
    (tmp_path / name).write_text("\n".join(",".join(r) for r in [list(columns), *rows]) + "\n")
    code, _, err = main_in_process(capsys, "plot", str(tmp_path))
    one_line(code, err, f"{tmp_path / name}: column {columns[2]!r} holds 'oops' in row 2, expected a number")


# -- the Python API's arguments, checked as the CLI's ------------------------------------------------


@pytest.mark.parametrize("seed", [-1, SEED_LIMIT, 2**40, 1.5, True])
def test_parallel_env_seed_out_of_range_names_the_seed(seed: Any) -> None:
    """It failed in SUMO, blaming the net."""
    from idas_sumo.env import MergeParallelEnv

    with pytest.raises(ValueError, match=r"^seed must be an integer in \[0, 2147483648\)"):
        MergeParallelEnv(DEFAULT_NET, seed=seed)


@pytest.mark.parametrize("copies", [0, 5000, 2.0])
def test_engine_copies_out_of_range(copies: Any) -> None:
    from idas_sumo.env.engine import MergeEngine

    with pytest.raises(ValueError, match=r"^copies must be an integer in \[1, 4096\]"):
        MergeEngine(DEFAULT_NET, copies=copies)


def test_a_config_that_is_not_an_env_config() -> None:
    from idas_sumo.env import MergeParallelEnv

    with pytest.raises(TypeError, match="config must be an EnvConfig, got dict"):
        MergeParallelEnv(DEFAULT_NET, config={"max_episode_s": 3.0})  # type: ignore[arg-type]


@pytest.mark.parametrize("value", [math.inf, math.nan, "30", 86_400.5, 0.0])
def test_max_episode_s_must_be_a_bounded_positive_number(value: Any) -> None:
    from idas_sumo.env.config import MAX_EPISODE_S

    with pytest.raises(ValueError, match=r"^max_episode_s must be positive and at most 86400 s"):
        EnvConfig(max_episode_s=value)
    assert EnvConfig(max_episode_s=MAX_EPISODE_S).max_episode_s == MAX_EPISODE_S


# -- a step after the episode ended ---------------------------------------------------------------


@pytest.mark.sumo
def test_gymnasium_step_after_the_episode_says_to_reset() -> None:
    """It was a KeyError; gymnasium's OrderEnforcing raises ResetNeeded for a step before reset()."""
    import gymnasium as gym
    from gymnasium.error import ResetNeeded

    from idas_sumo.errors import SimulationError

    env = gym.make("idas_sumo/Merge-v0")
    try:
        env.reset(seed=1)
        done = False
        while not done:
            _, _, terminated, truncated, _ = env.step(0)
            done = terminated or truncated
        for _ in range(2):
            with pytest.raises(ResetNeeded, match=r"after the episode ended .*call reset\(\)") as caught:
                env.step(0)
            assert isinstance(caught.value, SimulationError)
        env.reset(seed=2)
        env.step(0)  # a new episode steps again
    finally:
        env.close()


@pytest.mark.sumo
def test_parallel_step_with_no_agents_warns_and_leaves_the_simulation_alone(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """PettingZoo's convention (its OrderEnforcingWrapper): a warning and empty dicts; SUMO was stepped on."""
    from gymnasium.error import ResetNeeded

    from idas_sumo.env import MergeParallelEnv

    env = MergeParallelEnv(DEFAULT_NET, seed=3)
    try:
        with pytest.raises(ResetNeeded, match=r"before reset\(\)"):
            env.step({})
        env.reset(seed=4)
        while env.agents:
            env.step(dict.fromkeys(env.agents, 0))
        time_s = env.sim.time_s
        with caplog.at_level("WARNING"):
            assert env.step({"main0": 0}) == ({}, {}, {}, {}, {})
        assert env.sim.time_s == time_s
        assert "Should reset() first" in caplog.text
        env.reset(seed=5)
        assert env.agents
    finally:
        env.close()


# -- sweep: checked at the edge, and a stale run folder --------------------------------------------

TINY = """\
stage = "direct"
direct_episodes = 2
episodes_per_update = 2
checkpoint_every = 2
max_episode_s = 15.0
copies = 2
validate_every = 2
validation_scenarios = 2
"""


@pytest.mark.parametrize("seeds", [str(SEED_LIMIT), f"0-{SEED_LIMIT + 3}", "5,99999999999"])
def test_sweep_seeds_out_of_range_are_refused_before_anything_is_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], seeds: str
) -> None:
    """They failed late, blaming a cached net, and left a partial sweep folder."""
    config = tmp_path / "tiny.toml"
    config.write_text(TINY)
    out = tmp_path / "sweep"
    code, _, err = main_in_process(capsys, "sweep", str(config), "--seeds", seeds, "--out", str(out))
    one_line(code, err, "--seeds: seed", "outside [0, 2147483648)")
    assert not out.exists()


def test_plan_sweep_checks_the_seeds_it_is_given(tmp_path: Path) -> None:
    from idas_sumo.training.sweep import plan_sweep

    config = tmp_path / "tiny.toml"
    config.write_text(TINY)
    with pytest.raises(InputError, match="seeds: -1 is not an integer in"):
        plan_sweep(config, [0, -1], [])


@pytest.mark.sumo
def test_a_sweep_whose_config_changed_refuses_the_earlier_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A finished run was reused as if the changed config had trained it (train --resume warns)."""
    config = tmp_path / "tiny.toml"
    config.write_text(TINY)
    out = tmp_path / "sweep"
    args = ("sweep", str(config), "--seeds", "0", "--out", str(out), "--net", str(DEFAULT_NET))
    code, _, err = main_in_process(capsys, *args)
    assert code == 0, err
    table = (out / "sweep.csv").read_bytes()
    code, _, err = main_in_process(capsys, *args)  # unchanged: the finished run is read, not trained again
    assert code == 0, err
    assert (out / "sweep.csv").read_bytes() == table
    config.write_text(TINY.replace("max_episode_s = 15.0", "max_episode_s = 14.0") + "workers = 1\n")
    code, _, err = main_in_process(capsys, *args)
    one_line(code, err, f"{out / 'seed-0'}: trained by an earlier sweep with another config (env differ")
    assert (out / "sweep.csv").read_bytes() == table


# -- evaluate: a car that departs after the timeout ------------------------------------------------


@pytest.mark.parametrize("depart_s", ["1e300", "60.0"])
def test_a_car_departing_after_the_timeout_is_refused_and_nothing_is_left(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], depart_s: str
) -> None:
    """1e300 s: SUMO refused it after writing its tripinfo file into --out, so the rerun was refused."""
    text = (SCENARIO_DIR / "representative" / "s1.toml").read_text()
    scenario = tmp_path / "far.toml"
    scenario.write_text(text.replace("b_type = 1.0", f"b_type = 1.0\ndepart_s = {depart_s}"))
    out = tmp_path / "ev"
    args = ("evaluate", "--baseline", "idm", "--scenario", str(scenario), "--out", str(out))
    code, _, err = main_in_process(capsys, *args, "--sumo-output", "--no-progress")
    one_line(code, err, f"{scenario}: vehicle 'merge_car' departs at", "timeout (max_episode_s)")
    assert not out.exists()
