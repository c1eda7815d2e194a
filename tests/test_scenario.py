"""Scenario generation (seeded, within the design's ranges) and scenario TOML files (good and bad)."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from idas_sumo.env.actions import safety_bound
from idas_sumo.env.scenario import TrafficConfig, _speeds_without_braking, generate_scenario, load_scenario
from idas_sumo.errors import InputError

LIMITS = {"main": 20.0, "merge": 15.0}
# The first generator (2 to 8 cars per road, all at t = 0), which these tests pin; the paper's traffic
# (the default) is tested in test_paper_traffic.py.
DENSE = {"n_vehicles": 0, "min_vehicles_per_road": 2, "max_vehicles_per_road": 8}


def test_generate_is_deterministic_per_seed() -> None:
    a = generate_scenario(np.random.default_rng(7), TrafficConfig(), LIMITS)
    b = generate_scenario(np.random.default_rng(7), TrafficConfig(), LIMITS)
    c = generate_scenario(np.random.default_rng(8), TrafficConfig(), LIMITS)
    assert a == b
    assert a != c


def test_generated_ranges() -> None:
    traffic = TrafficConfig(start_without_braking=False, **DENSE)  # speeds exactly as drawn
    rng = np.random.default_rng(0)
    counts: set[int] = set()
    prios: set[tuple[int, int]] = set()
    for _ in range(300):
        s = generate_scenario(rng, traffic, LIMITS)
        prios.add((s.main_prio, s.merge_prio))
        for road in ("main", "merge"):
            cars = sorted((v for v in s.vehicles if v.road == road), key=lambda v: v.start_pos_m)
            counts.add(len(cars))
            assert 2 <= len(cars) <= 8
            for v in cars:
                assert 5.0 <= v.start_pos_m <= 200.0
                assert 0.6 * LIMITS[road] - 1e-3 <= v.speed_mps <= LIMITS[road] + 1e-3
                assert -2.0 <= v.b_type <= 2.0
                assert v.controlled and v.depart_s == 0.0
            for back, front in itertools.pairwise(cars):
                # front bumpers 5 m (a car) + 15 m (the minimum gap) apart, up to rounding to mm
                assert front.start_pos_m - back.start_pos_m >= 20.0 - 2e-3
    assert counts == set(range(2, 9))
    assert (1, 0) in prios and ((0, 0) in prios or (1, 1) in prios)


def test_start_speed_cap_hand_worked() -> None:
    # Leader at 9 m/s, follower 15 m behind (bumper gap): s* = 2 + v + v(v - 9)/4 <= 15 gives
    # v²/4 - 1.25·v - 13 <= 0, whose larger root is (1.25 + sqrt(1.5625 + 13)) / 0.5 = 10.132 m/s.
    capped = _speeds_without_braking(np.array([5.0, 25.0]), np.array([14.0, 9.0]))
    np.testing.assert_allclose(capped, [10.1322, 9.0], atol=1e-4)
    # A slower follower keeps its drawn speed.
    np.testing.assert_allclose(
        _speeds_without_braking(np.array([5.0, 25.0]), np.array([8.0, 9.0])), [8.0, 9.0]
    )


def test_no_car_starts_inside_its_safety_braking_region() -> None:
    rng = np.random.default_rng(3)
    drawn_off = TrafficConfig(start_without_braking=False, **DENSE)
    capped_any = False
    for _ in range(200):
        state = rng.bit_generator.state
        s = generate_scenario(rng, TrafficConfig(**DENSE), LIMITS)
        rng_off = np.random.default_rng()
        rng_off.bit_generator.state = state
        as_drawn = generate_scenario(rng_off, drawn_off, LIMITS)
        # Same draws: positions, types and priorities agree; speeds are only ever lowered.
        for v, w in zip(s.vehicles, as_drawn.vehicles, strict=True):
            assert (v.id, v.start_pos_m, v.b_type) == (w.id, w.start_pos_m, w.b_type)
            assert v.speed_mps <= w.speed_mps + 1e-9
            capped_any |= v.speed_mps < w.speed_mps - 1e-6
        for road in ("main", "merge"):
            cars = sorted((v for v in s.vehicles if v.road == road), key=lambda v: v.start_pos_m)
            for back, front in itertools.pairwise(cars):
                gap = front.start_pos_m - back.start_pos_m - 5.0
                bound = safety_bound([back.speed_mps], [gap], [front.speed_mps])[0]
                assert bound >= -0.01  # IDM asks for no braking at the start (up to mm rounding)
    assert capped_any


def test_max_controlled_makes_robot_cars() -> None:
    s = generate_scenario(np.random.default_rng(1), TrafficConfig(max_controlled=1), LIMITS)
    assert len(s.controlled_ids) == 1


GOOD = """
name = "two cars"
main_prio = 1
merge_prio = 0

[[vehicles]]
id = "m0"
road = "main"
start_pos_m = 100.0
speed_mps = 18.0
b_type = 1.5

[[vehicles]]
id = "g0"
road = "merge"
start_pos_m = 90.0
speed_mps = 12.0
b_type = -2.0
controlled = false
"""


def _write(tmp_path: Path, text: str, name: str = "s.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_load_good(tmp_path: Path) -> None:
    s = load_scenario(_write(tmp_path, GOOD), LIMITS)
    assert s.name == "two cars"
    assert [(v.id, v.road, v.start_pos_m, v.speed_mps, v.b_type, v.controlled) for v in s.vehicles] == [
        ("m0", "main", 100.0, 18.0, 1.5, True),
        ("g0", "merge", 90.0, 12.0, -2.0, False),
    ]
    assert s.controlled_ids == ("m0",)


def _vehicle(**fields: object) -> str:
    base: dict[str, object] = {"id": '"m0"', "road": '"main"', "start_pos_m": 100.0, "speed_mps": 10.0}
    base.update(fields)
    return "[[vehicles]]\n" + "".join(f"{k} = {v}\n" for k, v in base.items())


BAD = {
    "unknown_key": (_vehicle(start_pos=3.0), ["unknown key", 'did you mean "start_pos_m"']),
    "top_level_typo": ("main_prioo = 1\n" + _vehicle(), ['did you mean "main_prio"']),
    "b_type_3": (_vehicle(b_type=3.0), ["b_type"]),
    "b_type_nan": (_vehicle(b_type="nan"), ["b_type", "finite"]),
    "negative_speed": (_vehicle(speed_mps=-1.0), ["negative speed"]),
    "overlap": (
        _vehicle() + _vehicle(id='"m1"', start_pos_m=102.0),
        ["overlap"],
    ),
    "priority_2": ("main_prio = 2\n" + _vehicle(), ["main_prio"]),
    "bad_road": (_vehicle(road='"side"'), ["road"]),
    "speed_above_limit": (_vehicle(speed_mps=25.0), ["above", "limit"]),
    "no_vehicles": ('name = "empty"\n', ["at least one vehicle"]),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_load_bad(tmp_path: Path, case: str) -> None:
    text, fragments = BAD[case]
    p = _write(tmp_path, text, f"{case}.toml")
    with pytest.raises(InputError) as info:
        load_scenario(p, LIMITS)
    message = str(info.value)
    assert str(p) in message, message
    assert "\n" not in message, message
    for fragment in fragments:
        assert fragment in message, message


def test_syntax_error_names_file_and_line(tmp_path: Path) -> None:
    p = _write(tmp_path, 'name = "x"\nmain_prio = 1\nmerge_prio = = 0\n')
    with pytest.raises(InputError) as info:
        load_scenario(p)
    message = str(info.value)
    assert str(p) in message and "line 3" in message, message


def test_missing_file(tmp_path: Path) -> None:
    p = tmp_path / "missing.toml"
    with pytest.raises(InputError, match=r"missing\.toml"):
        load_scenario(p)
