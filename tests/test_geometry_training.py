"""Training with ``[geometry]``: a generated merge drawn per round from the config's ranges (on a
grid, from the run's seed), the rollout workers switching nets with the rounds, validation on the
run's own net (or on merges drawn by the validation seed), ``geometries.csv``; bad ranges are one
line, exit 2; the default ranges leave out the held-out geometries of ``evaluate --suite geometry``."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from idas_sumo.cli import main
from idas_sumo.env.config import EnvConfig
from idas_sumo.env.scenario import TrafficConfig
from idas_sumo.errors import InputError
from idas_sumo.evaluation.geometry import HELD_OUT_GEOMETRIES
from idas_sumo.resources import DEFAULT_TRAIN_CONFIG, SCENARIO_DIR
from idas_sumo.sim.net_cache import cached_net
from idas_sumo.sim.netgen import NetParams
from idas_sumo.training.config import TrainConfig, load_train_config
from idas_sumo.training.geometry import GRID, GeometryConfig, draw_geometry

EXPERIMENT_RECIPES = Path(__file__).resolve().parents[1] / "experiments" / "recipes"
RANGES = GeometryConfig(
    main_length_m=(230.0, 260.0),
    merge_length_m=(230.0, 260.0),
    out_length_m=(140.0, 160.0),
    angle_deg=(20.0, 40.0),
    equal_priority_probability=0.5,
)
"""Short approaches, so that the tiny runs' short episodes fit every draw."""


def tiny_config(**changes: Any) -> TrainConfig:
    """Two rounds of two episodes, few cars, short episodes, a geometry per round."""
    base = TrainConfig(
        stage="direct",
        direct_episodes=4,
        episodes_per_update=2,
        checkpoint_every=2,
        intelligent_traffic=TrafficConfig(n_vehicles=0, min_vehicles_per_road=1, max_vehicles_per_road=2),
        env=EnvConfig(max_episode_s=15.0),
        geometry=RANGES,
    )
    return dataclasses.replace(base, **changes)


def rows(path: Path, drop: tuple[str, ...] = ("wall_time_s",)) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return [{k: v for k, v in r.items() if k not in drop} for r in csv.DictReader(f)]


@pytest.fixture(scope="module")
def _module_net_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("net_cache")


@pytest.fixture
def net_cache(_module_net_cache: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """One cache for the module's runs: they draw the same geometries, so each net is built once."""
    monkeypatch.setenv("IDAS_SUMO_CACHE", str(_module_net_cache))
    return _module_net_cache


@pytest.fixture
def fresh_net_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    cache = tmp_path / "cache"
    monkeypatch.setenv("IDAS_SUMO_CACHE", str(cache))
    return cache


# --- the ranges -------------------------------------------------------------------------------------


def test_geometry_is_off_by_default_and_only_in_the_geometry_recipes() -> None:
    assert TrainConfig().geometry is None
    for recipe in sorted(SCENARIO_DIR.glob("train_*.toml")):
        config = load_train_config(recipe)
        assert (config.geometry is not None) == recipe.name.startswith("train_geometry"), recipe
    assert load_train_config(DEFAULT_TRAIN_CONFIG).geometry is None


def test_the_geometry_recipes_are_the_shipped_ones_with_the_default_ranges() -> None:
    # The earlier geometry recipes and the FSM+IDM-start recipes they extend live in experiments/recipes.
    stage1 = load_train_config(EXPERIMENT_RECIPES / "train_geometry.toml")
    stage2 = load_train_config(EXPERIMENT_RECIPES / "train_geometry_stage2.toml")
    assert stage1.geometry == stage2.geometry == GeometryConfig()
    assert dataclasses.replace(stage1, geometry=None) == load_train_config(
        EXPERIMENT_RECIPES / "train_shipped.toml"
    )
    shipped2 = load_train_config(EXPERIMENT_RECIPES / "train_shipped_stage2_safety.toml")
    assert dataclasses.replace(stage2, geometry=None) == shipped2  # from IDAS-V too
    validated = load_train_config(EXPERIMENT_RECIPES / "train_geometry_stage2_validated.toml")
    assert validated == dataclasses.replace(
        stage2,
        intelligent_episodes=2000,
        validate_every=200,
        geometry=GeometryConfig(validation_geometries=8),
    )
    equal = load_train_config(SCENARIO_DIR / "train_geometry_stage2_equal.toml")
    assert equal == dataclasses.replace(
        validated,
        validation_scenarios=80,
        geometry=GeometryConfig(validation_geometries=8, equal_approaches_probability=0.5),
    )
    assert equal.geometry is not None
    for name, params in HELD_OUT_GEOMETRIES:
        assert not equal.geometry.can_draw(params), name


def test_default_ranges_cannot_draw_a_held_out_geometry() -> None:
    defaults = GeometryConfig()
    for name, params in HELD_OUT_GEOMETRIES:
        assert not defaults.can_draw(params), name
    assert defaults.can_draw(NetParams())  # the shipped T-junction is one of them
    # A config may say otherwise: then it can.
    wide = GeometryConfig(angle_deg=(10.0, 70.0))
    assert wide.can_draw(dict(HELD_OUT_GEOMETRIES)["angle-15"])
    zipper = dataclasses.replace(GeometryConfig(), equal_priority_probability=1.0)
    assert not zipper.can_draw(NetParams())


def test_draws_lie_on_the_grid_within_the_ranges_and_follow_the_seed() -> None:
    ranges = GeometryConfig()
    draws = [draw_geometry(np.random.default_rng(5), ranges) for _ in range(2)]
    assert draws[0] == draws[1]
    rng = np.random.default_rng(0)
    many = [draw_geometry(rng, ranges) for _ in range(300)]
    for name, step in GRID.items():
        values = np.array([getattr(p, name) for p in many])
        lo, hi = getattr(ranges, name)
        assert values.min() >= lo and values.max() <= hi, name
        assert np.allclose(values / step, np.round(values / step)), name
        assert len(set(values.tolist())) > 3, name
    assert {p.priority for p in many} == {"main"}
    half = dataclasses.replace(ranges, equal_priority_probability=0.5)
    assert {draw_geometry(rng, half).priority for _ in range(50)} == {"main", "equal"}


def test_equal_approaches_make_the_merging_road_as_long_as_the_main_road_at_that_rate() -> None:
    """With ``equal_approaches_probability`` = 0.5 about half the draws have two equal approaches (drawn
    independently, almost none do); at 0 the generator draws exactly as before the option existed."""
    ranges = GeometryConfig()
    half = dataclasses.replace(ranges, equal_approaches_probability=0.5)
    rng = np.random.default_rng(1)
    draws = [draw_geometry(rng, half) for _ in range(400)]
    equal = np.mean([p.main_length_m == p.merge_length_m for p in draws])
    assert 0.42 < equal < 0.58
    assert all(half.can_draw(p) for p in draws)
    # At 0 a draw takes one integer per grid value and one float (the priority), as before the option.
    drawn, by_hand = np.random.default_rng(1), np.random.default_rng(1)
    draw_geometry(drawn, ranges)
    for name, step in GRID.items():
        lo, hi = getattr(ranges, name)
        by_hand.integers(0, round((hi - lo) / step) + 1)
    by_hand.random()
    assert drawn.random() == by_hand.random()
    always = dataclasses.replace(ranges, equal_approaches_probability=1.0)
    assert not always.can_draw(dataclasses.replace(NetParams(), main_length_m=250.0, merge_length_m=260.0))
    with pytest.raises(InputError, match="same range"):
        dataclasses.replace(ranges, merge_length_m=(230.0, 300.0), equal_approaches_probability=0.5)


@pytest.mark.parametrize(
    ("table", "needle"),
    [
        ("angle_deg = [40, 30]", "angle_deg: low 40 is above high 30"),
        ("angle_deg = [2, 30]", "outside [5, 90]"),
        ("main_length_m = [230.5, 300]", "not on the 1 m grid"),
        ("main_speed_mps = [18.2, 20]", "not on the 0.5 m/s grid"),
        ("merge_length_m = [230, 260, 300]", "expected [low, high]"),
        ("equal_priority_probability = 1.5", "must be in [0, 1]"),
        ("equal_approaches_probability = -0.1", "must be in [0, 1]"),
        ("out_speed_mps = 'fast'", "expected a list"),
        ("angle = [20, 30]", "did you mean"),
        ("main_length_m = [230, 3000]", "[geometry]: ranges draw a net the scenarios cannot use"),
    ],
)
def test_bad_ranges_are_one_line_exit_2(
    tmp_path: Path,
    net_path: Path,
    net_cache: Path,
    capsys: pytest.CaptureFixture[str],
    table: str,
    needle: str,
) -> None:
    config = tmp_path / "bad.toml"
    config.write_text(f'stage = "direct"\ndirect_episodes = 2\n\n[geometry]\n{table}\n')
    out = tmp_path / "run"
    code = main(
        ["train", "--net", str(net_path), "--config", str(config), "--out", str(out), "--no-progress"]
    )
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err and needle in err, err
    assert not (out / "metrics.csv").exists()


# --- runs ---------------------------------------------------------------------------------------------


@pytest.fixture
def engine_sites(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, int]]:
    """(net file name, tasks) of every batch an in-process worker runs, read from its engine's site."""
    import idas_sumo.training.workers as workers

    seen: list[tuple[str, int]] = []
    original = workers._run_tasks

    def spy(engine: Any, learner: Any, tasks: list[Any]) -> Any:
        seen.append((engine.site.path.name, len(tasks)))
        return original(engine, learner, tasks)

    monkeypatch.setattr(workers, "_run_tasks", spy)
    return seen


@pytest.mark.sumo
def test_each_round_runs_on_its_drawn_net_and_validation_on_the_runs_own(
    net_path: Path, tmp_path: Path, net_cache: Path, engine_sites: list[tuple[str, int]]
) -> None:
    from idas_sumo.training.loop import run_training

    run = tmp_path / "run"
    config = tiny_config(validate_every=4, validation_scenarios=2)
    run_training(net_path, config, run, progress=False)
    geometries = rows(run / "geometries.csv")
    assert [(g["stage"], g["episode"], g["global_episode"], g["episodes"]) for g in geometries] == [
        ("direct", "0", "0", "2"),
        ("direct", "2", "2", "2"),
    ]
    nets = [g["net"] for g in geometries]
    assert nets[0] != nets[1] and all((net_cache / "gen" / n).is_file() for n in nets)
    # The rounds ran on the drawn nets, the validation (2 scenarios) on the run's own.
    assert engine_sites == [(nets[0], 2), (nets[1], 2), (net_path.name, 2)]
    for g in geometries:
        params = NetParams(**{k: float(g[k]) for k in GRID}, priority=g["priority"])
        assert RANGES.can_draw(params)
    metrics = rows(run / "metrics.csv")
    assert len(metrics) == 4 and list(metrics[0]) == list(rows(run / "metrics.csv")[0])


@pytest.mark.sumo
def test_validation_geometries_validate_on_merges_drawn_by_the_validation_seed(
    net_path: Path, tmp_path: Path, net_cache: Path, engine_sites: list[tuple[str, int]]
) -> None:
    """With ``validation_geometries`` the validation scenarios (3 over 2 merges: 2 and 1) run on merges
    drawn from the ranges by the validation seed, the same ones at both validations, none the run's net."""
    from idas_sumo.training.loop import run_training

    ranges = dataclasses.replace(RANGES, validation_geometries=2)
    config = tiny_config(geometry=ranges, validate_every=2, validation_scenarios=3, validation_seed=5)
    run_training(net_path, config, tmp_path / "run", progress=False)
    rounds = [g["net"] for g in rows(tmp_path / "run" / "geometries.csv")]
    assert [site for site, _ in engine_sites[:1]] == rounds[:1]
    validation = [e for e in engine_sites if e[0] not in rounds]
    assert [n for _, n in validation] == [2, 1, 2, 1]  # two validations, each over the two merges
    first, second = validation[:2], validation[2:]
    assert first == second and first[0][0] != first[1][0]
    assert net_path.name not in {site for site, _ in engine_sites}
    rng = np.random.default_rng(5)
    expected = [draw_geometry(rng, ranges) for _ in range(2)]
    assert [site for site, _ in first] == [cached_net(p).name for p in expected]
    assert all(ranges.can_draw(p) for p in expected)
    assert len(rows(tmp_path / "run" / "validation.csv")) == 2
    # Another validation seed draws other merges.
    other = tiny_config(geometry=ranges, validate_every=2, validation_scenarios=3, validation_seed=6)
    engine_sites.clear()
    run_training(net_path, other, tmp_path / "other", progress=False)
    rounds = [g["net"] for g in rows(tmp_path / "other" / "geometries.csv")]
    assert {e[0] for e in engine_sites if e[0] not in rounds} != {site for site, _ in first}


@pytest.mark.sumo
def test_the_same_seed_gives_the_same_run_and_workers_change_nothing(
    net_path: Path, tmp_path: Path, net_cache: Path
) -> None:
    from idas_sumo.training.loop import run_training

    config = tiny_config()
    run_training(net_path, config, tmp_path / "a", progress=False)
    run_training(net_path, config.with_overrides(workers=2), tmp_path / "w2", progress=False)
    first = rows(tmp_path / "a" / "metrics.csv")
    assert len(first) == 4 and len({r["return_mean"] for r in first}) > 1
    # Two workers must give the one-worker run's rows: so the same seed does too.
    assert rows(tmp_path / "w2" / "metrics.csv") == first
    assert rows(tmp_path / "w2" / "geometries.csv") == rows(tmp_path / "a" / "geometries.csv")
    assert (
        rows(tmp_path / "a" / "geometries.csv")[0]["net"] != rows(tmp_path / "a" / "geometries.csv")[1]["net"]
    )
    other_seed = tmp_path / "seed1"
    run_training(net_path, config.with_overrides(seed=1), other_seed, progress=False)
    assert rows(other_seed / "geometries.csv") != rows(tmp_path / "a" / "geometries.csv")


@pytest.mark.sumo
def test_a_run_extended_on_resume_draws_as_one_straight_run(
    net_path: Path, tmp_path: Path, net_cache: Path
) -> None:
    from idas_sumo.training.loop import run_training

    straight = tmp_path / "straight"
    run_training(net_path, tiny_config(direct_episodes=6), straight, progress=False)
    run = tmp_path / "run"
    run_training(net_path, tiny_config(direct_episodes=2), run, progress=False)
    run_training(net_path, tiny_config(direct_episodes=6), run, resume=True, progress=False)
    assert rows(run / "geometries.csv") == rows(straight / "geometries.csv")
    assert rows(run / "metrics.csv") == rows(straight / "metrics.csv")
    assert len(rows(run / "geometries.csv")) == 3


def test_a_drawn_net_is_checked_against_the_runs_roads(tmp_path: Path, net_cache: Path) -> None:
    """Episodes too short for the longest draw: refused before the run starts."""
    from idas_sumo.resources import DEFAULT_NET
    from idas_sumo.training.loop import run_training

    config = tiny_config(env=EnvConfig(max_episode_s=6.0))
    with pytest.raises(InputError, match=r"\[geometry\]"):
        run_training(DEFAULT_NET, config, tmp_path / "run", progress=False)
    assert not (tmp_path / "run" / "metrics.csv").exists()


@pytest.mark.sumo
def test_ray_actors_switch_nets_as_local_workers_do(
    tmp_path: Path, net_path: Path, net_cache: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The round's net goes to Ray actors with the tasks: the same run as with local processes."""
    config = tmp_path / "geometry.toml"
    config.write_text(
        'stage = "direct"\ndirect_episodes = 4\nepisodes_per_update = 2\ncheckpoint_every = 2\n'
        "max_episode_s = 15.0\ncopies = 2\n\n[geometry]\nmain_length_m = [230, 260]\n"
        "merge_length_m = [230, 260]\nangle_deg = [20, 40]\n"
    )
    common = ["train", "--net", str(net_path), "--config", str(config), "--workers", "2", "--no-progress"]
    assert main([*common, "--out", str(tmp_path / "local")]) == 0
    assert main([*common, "--out", str(tmp_path / "ray"), "--ray-address", "local"]) == 0, (
        capsys.readouterr().err
    )
    for name in ("metrics.csv", "geometries.csv"):
        assert rows(tmp_path / "ray" / name) == rows(tmp_path / "local" / name), name
    nets = [g["net"] for g in rows(tmp_path / "local" / "geometries.csv")]
    assert len(nets) == 2 and nets[0] != nets[1]


def test_the_build_ahead_reads_the_next_draw_without_taking_it(tmp_path: Path, fresh_net_cache: Path) -> None:
    """The next round's nets are built while a round runs: from a copy of the run's generator, which
    itself does not move (the round then draws that very geometry)."""
    from idas_sumo.env.net_needs import road_needs
    from idas_sumo.sim.net_cache import cached_net
    from idas_sumo.training.loop import _GeometryDraws
    from idas_sumo.training.metrics import MetricsSink

    with MetricsSink(tmp_path, name="g.csv", columns=("global_episode",), tensorboard_keys=()) as sink:
        draws = _GeometryDraws(RANGES, road_needs(200.0, 40.0), sink, copies=1)
        rng = np.random.default_rng(11)
        before = rng.bit_generator.state
        draws.prefetch(rng)
        assert rng.bit_generator.state == before
        draws.wait()
        built = sorted((fresh_net_cache / "gen").glob("*.net.xml"))
        params, site = draws.draw(rng)
    assert params == draw_geometry(np.random.default_rng(11), RANGES)
    assert built == [cached_net(params)] == [site.path]
