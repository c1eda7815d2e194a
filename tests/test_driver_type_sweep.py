"""The driver-type sweep (issue #15 item 4; evaluation/sweep.py): the rank correlation against hand-worked
numbers, the sweep's scenarios (paper Fig. 5(a): both cars reach the merging zone together, the merge car not
ahead), its tables, and the suite end to end on a tiny budget."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from idas_sumo.cli import main
from idas_sumo.errors import InputError
from idas_sumo.evaluation.sweep import (
    DRIVER_TYPE_COLUMNS,
    MAIN_CAR_B_TYPE,
    SIGNIFICANCE,
    SWEEP_B_TYPES,
    TREND_COLUMNS,
    average_ranks,
    driver_type_rows,
    is_sweep_scenario,
    spearman,
    spearman_test,
    sweep_scenarios,
    trend_rows,
    verdict,
)

LIMITS = {"main": 20.0, "merge": 15.0}
LENGTHS = {"main": 250.0, "merge": 250.0}

# --- the rank correlation -----------------------------------------------------------------------------


def test_average_ranks_share_ties() -> None:
    np.testing.assert_allclose(average_ranks([1, 2, 2, 3]), [1.0, 2.5, 2.5, 4.0])
    np.testing.assert_allclose(average_ranks([3.0, 1.0, 3.0, 3.0, 0.5]), [4.0, 2.0, 4.0, 4.0, 1.0])
    np.testing.assert_allclose(average_ranks([]), [])


def test_spearman_hand_worked_with_ties() -> None:
    """x = 1, 2, 2, 3 -> ranks 1, 2.5, 2.5, 4; y = 1, 3, 2, 4 -> ranks 1, 3, 2, 4.
    Centred: dx = -1.5, 0, 0, 1.5 and dy = -1.5, 0.5, -0.5, 1.5; sum dx*dy = 4.5, sum dx^2 = 4.5,
    sum dy^2 = 5; rho = 4.5 / sqrt(4.5 * 5) = 3 / sqrt(10) = 0.9487."""
    assert spearman([1, 2, 2, 3], [1, 3, 2, 4]) == pytest.approx(3.0 / math.sqrt(10.0))
    # Only the order matters: any increasing transform of either side gives the same rho.
    assert spearman([10, 20, 20, 300], np.exp([1, 3, 2, 4])) == pytest.approx(3.0 / math.sqrt(10.0))
    assert spearman([1, 2, 2, 3], [4, 2, 3, 1]) == pytest.approx(-3.0 / math.sqrt(10.0))


def test_spearman_extremes_and_undefined() -> None:
    assert spearman([1, 2, 3, 4], [2, 4, 6, 9]) == pytest.approx(1.0)
    assert spearman([1, 2, 3, 4], [9, 6, 4, 2]) == pytest.approx(-1.0)
    # x tied within groups, y equal for every x: exactly zero (a policy that ignores b_type).
    assert spearman([-2, -2, 0, 0, 2, 2], [5, 7, 5, 7, 5, 7]) == pytest.approx(0.0)
    assert math.isnan(spearman([1, 2, 3], [5, 5, 5]))
    assert math.isnan(spearman([], []))
    with pytest.raises(ValueError, match="same length"):
        spearman([1, 2], [1, 2, 3])


def test_permutation_p_value_matches_the_exact_one() -> None:
    """n = 4, rho = 1: of the 24 orders of y, two reach |rho| = 1 (the identity and the reversal), so the
    exact two-sided p is 2/24."""
    rho, p = spearman_test([1, 2, 3, 4], [1, 2, 3, 4], permutations=20_000)
    assert rho == pytest.approx(1.0)
    assert p == pytest.approx(2 / 24, abs=0.01)
    # The same inputs give the same p (fixed seed).
    assert spearman_test([1, 2, 3, 4], [1, 2, 3, 4], permutations=20_000) == (rho, p)


def test_permutation_p_value_bounds() -> None:
    x = np.arange(20)
    # 2 of 20! orders reach |rho| = 1: no permutation does, and p is the smallest the test can give.
    assert spearman_test(x, x**2, permutations=1000) == (pytest.approx(1.0), pytest.approx(1 / 1001))
    # rho = 0 exactly: every permutation is at least as extreme.
    _, p = spearman_test([-2, -2, 0, 0, 2, 2], [5, 7, 5, 7, 5, 7], permutations=500)
    assert p == 1.0
    assert all(math.isnan(v) for v in spearman_test([1, 2, 3], [5, 5, 5]))


# --- the sweep's scenarios ----------------------------------------------------------------------------


def test_sweep_scenarios_reach_the_merging_zone_together_merge_car_not_ahead() -> None:
    cases = sweep_scenarios(4, 2019, LIMITS, LENGTHS)
    assert len(cases) == 4 * len(SWEEP_B_TYPES)
    np.testing.assert_allclose(SWEEP_B_TYPES, np.linspace(-2.0, 2.0, 9))
    for i, case in enumerate(cases):
        main_car, merge_car = case.scenario.vehicles
        assert case.merge_car == merge_car.id
        assert (main_car.road, merge_car.road) == ("main", "merge")
        assert (case.scenario.main_prio, case.scenario.merge_prio) == (1, 0)
        assert main_car.b_type == MAIN_CAR_B_TYPE
        assert merge_car.b_type == SWEEP_B_TYPES[i % len(SWEEP_B_TYPES)]
        d_main = LENGTHS["main"] - main_car.start_pos_m
        d_merge = LENGTHS["merge"] - merge_car.start_pos_m
        assert d_merge >= d_main  # not ahead in projection
        assert main_car.speed_mps == merge_car.speed_mps <= min(LIMITS.values())
        # Without interaction both reach the merge point (and the zone's edge) within half a second.
        assert d_merge / merge_car.speed_mps - d_main / main_car.speed_mps < 0.5
        assert is_sweep_scenario(case.scenario.name)
    # Every b_type of one offset starts the same; offsets differ.
    starts = [(c.scenario.vehicles[0].start_pos_m, c.scenario.vehicles[1].start_pos_m) for c in cases]
    for k in range(4):
        assert len(set(starts[9 * k : 9 * k + 9])) == 1
    assert len(set(starts)) == 4
    # The seed draws the offsets: the same seed the same scenarios, another seed others.
    assert [c.scenario for c in sweep_scenarios(4, 2019, LIMITS, LENGTHS)] == [c.scenario for c in cases]
    assert sweep_scenarios(1, 7, LIMITS, LENGTHS)[0].scenario != cases[0].scenario


def test_sweep_on_roads_too_short_is_an_input_error() -> None:
    # 170 m at most before the merge point, 6 m more for the merge car, a car length: 181 m, whatever the seed.
    for seed in range(5):
        with pytest.raises(InputError, match=r"needs roads of at least 181 m .* merge road is 180 m"):
            sweep_scenarios(1, seed, LIMITS, {"main": 250.0, "merge": 180.0})
    assert len(sweep_scenarios(1, 0, LIMITS, {"main": 181.0, "merge": 181.0})) == len(SWEEP_B_TYPES)


def test_sweep_scenario_names() -> None:
    assert is_sweep_scenario("sweep03-btype-1.5") and is_sweep_scenario("s1-btype+2.0")
    assert not is_sweep_scenario("s1") and not is_sweep_scenario("paper-001")


# --- the tables ---------------------------------------------------------------------------------------


def _sweep_episodes() -> pd.DataFrame:
    """Method 'a': merge time rises with b_type; 'b': ignores it, and one episode never merged."""
    rows = []
    for method in ("a", "b"):
        for k in range(3):
            for b in (-2.0, 0.0, 2.0):
                merge = 10.0 + k + (b if method == "a" else 0.0)
                missing = method == "b" and k == 2 and b == 2.0
                rows.append(
                    {
                        "scenario": f"sweep{k:02d}-btype{b:+.1f}",
                        "method": method,
                        "ego_type": b,
                        "ego_merge_time_s": np.nan if missing else merge,
                        "ego_merge_speed_mps": np.nan if missing else 100.0 / merge,
                        "collisions": int(missing),
                        "ego_success": int(not missing),
                    }
                )
    rows.append({**rows[0], "scenario": "paper-000"})  # not part of the sweep
    return pd.DataFrame(rows)


def test_driver_type_rows_hand_computed() -> None:
    rows = driver_type_rows(_sweep_episodes())
    assert all(list(r) == list(DRIVER_TYPE_COLUMNS) for r in rows)
    assert [(r["method"], r["b_type"]) for r in rows] == [(m, b) for m in "ab" for b in (-2.0, 0.0, 2.0)]
    a_minus = rows[0]
    assert (a_minus["episodes"], a_minus["merged"]) == (3, 3)  # paper-000 left out
    assert a_minus["merge_time_mean_s"] == pytest.approx(9.0)  # 8, 9, 10
    assert a_minus["merge_time_sd_s"] == pytest.approx(1.0)
    assert (a_minus["merge_time_min_s"], a_minus["merge_time_max_s"]) == (8.0, 10.0)
    assert a_minus["merge_speed_mean_mps"] == pytest.approx(np.mean([100 / 8, 100 / 9, 100 / 10]), abs=1e-3)
    b_plus = rows[-1]
    assert (b_plus["episodes"], b_plus["merged"]) == (3, 2)
    assert b_plus["merge_time_mean_s"] == pytest.approx(10.5)
    assert b_plus["collision_pct"] == pytest.approx(100 / 3, abs=0.01)
    assert b_plus["ego_success_pct"] == pytest.approx(200 / 3, abs=0.01)


def test_trend_rows_and_verdicts() -> None:
    a, b = trend_rows(_sweep_episodes(), permutations=2000)
    assert list(a) == list(TREND_COLUMNS)
    # 'a': merge times 8,9,10 | 10,11,12 | 12,13,14 for b_type -2, 0, 2. Ranks: x 2,2,2,5,5,5,8,8,8;
    # y 1,2,3.5,3.5,5,6.5,6.5,8,9. Centred on 5: sum dx*dy = 3*8.5 + 3*8.5 = 51, sum dx^2 = 54,
    # sum dy^2 = 59; rho = 51 / sqrt(54 * 59) = 0.90354.
    x = [-2.0] * 3 + [0.0] * 3 + [2.0] * 3
    y = [8, 9, 10, 10, 11, 12, 12, 13, 14]
    assert a["spearman_rho"] == pytest.approx(spearman(x, y), abs=1e-4)
    assert a["spearman_rho"] == pytest.approx(51 / math.sqrt(54 * 59), abs=1e-4)
    assert a["direction"] == "rises" and a["significant"] == 1 and float(a["p_value"]) < SIGNIFICANCE  # type: ignore[arg-type]
    assert (a["episodes"], a["merged"]) == (9, 9)
    # 'b' ignores b_type, but one merge is missing at b_type 2 (the slowest offset): rho is slightly
    # negative and far from significant.
    assert (b["episodes"], b["merged"]) == (9, 8)
    assert b["direction"] == "falls" and b["significant"] == 0 and float(b["p_value"]) > 0.5  # type: ignore[arg-type]
    line_a = verdict(a, "A", "IDAS")
    assert "merge time rises with b_type, significant" in line_a and "rho = +0.903" in line_a
    line_b = verdict(b, "B", "IDAS")
    assert (
        "no significant trend" in line_b and "(sign: falls)" in line_b and "8 of 9 episodes merged" in line_b
    )
    assert "\n" not in line_a + line_b


def test_verdict_without_a_correlation() -> None:
    episodes = _sweep_episodes()
    episodes["ego_merge_time_s"] = 11.0  # no variation at all
    row = trend_rows(episodes, permutations=10)[0]
    assert math.isnan(row["spearman_rho"]) and row["direction"] == "undefined"  # type: ignore[arg-type]
    assert "no rank correlation" in verdict(row, "A", "IDAS")


# --- end to end -----------------------------------------------------------------------------------------


@pytest.mark.sumo
def test_driver_types_suite_on_a_tiny_budget(
    tmp_path: Path, net_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """IDM has no driver type: at every start offset its merge time is the same for every b_type, so the
    rank correlation is exactly zero, p = 1 and the verdict says there is no trend."""
    out = tmp_path / "sweep"
    args = [
        "evaluate",
        "--net",
        str(net_path),
        "--baseline",
        "idm",
        "--others",
        "idm",
        "--suite",
        "driver-types",
    ]
    assert main([*args, "--scenarios", "2", "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    episodes = pd.read_csv(out / "episodes.csv")
    table = pd.read_csv(out / "driver_types.csv")
    trend = pd.read_csv(out / "driver_types_trend.csv")
    assert list(table.columns) == list(DRIVER_TYPE_COLUMNS) and list(trend.columns) == list(TREND_COLUMNS)
    assert len(episodes) == 18 and episodes["ego_merge_time_s"].notna().all()
    per_offset = episodes.groupby(episodes["scenario"].str.slice(0, 7))["ego_merge_time_s"].nunique()
    assert (per_offset == 1).all()
    assert episodes["ego_merge_time_s"].nunique() == 2  # the two offsets differ
    assert table["b_type"].tolist() == list(SWEEP_B_TYPES)
    assert (table["episodes"] == 2).all() and (table["merged"] == 2).all()
    means = episodes.groupby("ego_type")["ego_merge_time_s"].mean()
    np.testing.assert_allclose(table["merge_time_mean_s"], means.to_numpy(), atol=1e-3)
    row = trend.iloc[0]
    assert (row["method"], row["merged"], row["spearman_rho"], row["p_value"]) == ("idm", 18, 0.0, 1.0)
    assert row["direction"] == "flat" and row["significant"] == 0
    verdict_lines = [line for line in printed.splitlines() if line.startswith("driver types, merge car IDM")]
    assert len(verdict_lines) == 1 and "no significant trend" in verdict_lines[0], printed
    assert "driver_types.csv, driver_types_trend.csv" in printed
