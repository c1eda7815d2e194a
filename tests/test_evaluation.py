"""`idas-sumo evaluate`: the CSV contract (docs/design-notes.md, "Evaluation output"), determinism, numbers that agree with the
trajectories, the suites, and the metric functions on hand-computed trajectories."""

from __future__ import annotations

import csv
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import evaluate_args

from idas_sumo.cli import main
from idas_sumo.evaluation.metrics import (
    BASE_EPISODE_COLUMNS,
    EPISODE_COLUMNS,
    FLOW_COLUMNS,
    SUMMARY_COLUMNS,
    EpisodeFacts,
    episode_row,
    finish_times,
    flow_row,
    merge_crossings,
    summary_rows,
)
from idas_sumo.io_utils import MANIFEST_NAME
from idas_sumo.resources import shipped

# The column lists exactly as docs/design-notes.md ("Evaluation output") spells them (not imported: this is the contract).
DESIGN_EPISODE_COLUMNS = [
    "scenario", "seed", "method", "ego_id", "ego_road", "ego_prio", "ego_type", "success", "perfect",
    "collisions", "hard_brakes", "hard_brakes_merge_zone", "ego_finish_time_s", "ego_mean_speed_mps",
    "mean_speed_mps", "total_reward", "normalized_reward",
    # issue #15, at the end so that readers of the first columns keep working
    "perfect_no_flow", "timeout", "ego_success", "ego_travel_time_s", "ego_merge_time_s", "ego_merge_speed_mps",
]  # fmt: skip
DESIGN_SUMMARY_COLUMNS = [
    "method", "scenarios", "success_pct", "perfect_pct", "avg_speed_perfect_mps",
    "perfect_no_flow_pct", "collision_pct", "timeout_pct", "ego_success_pct",
]  # fmt: skip
DESIGN_FLOW_COLUMNS = [
    "scenario", "method", "vehicles", "throughput_veh_per_h", "mean_speed_mps", "mean_travel_time_s",
    "mean_time_loss_s", "hard_brakes", "merge_time_s",
]  # fmt: skip
CSV_NAMES = ("episodes.csv", "summary.csv", "flow.csv")
N_SCENARIOS = 4


def evaluate(out: Path, net: Path, *extra: str) -> None:
    """Run `idas-sumo evaluate` in-process; the other vehicles run IDM so no policy file is needed."""
    args = ["evaluate", "--net", str(net), "--out", str(out), "--others", "idm", "--no-progress", *extra]
    assert main(args) == 0


def header(path: Path) -> list[str]:
    with path.open(newline="") as f:
        return next(csv.reader(f))


@pytest.fixture(scope="module")
def idm_run(tmp_path_factory: pytest.TempPathFactory, net_path: Path) -> Path:
    """IDM on a few paper scenarios, with trajectories."""
    out = tmp_path_factory.mktemp("idm")
    evaluate(
        out, net_path, "--baseline", "idm", "--scenarios", str(N_SCENARIOS), "--seed", "7", "--trajectories"
    )
    return out


@pytest.fixture(scope="module")
def fsm_run(tmp_path_factory: pytest.TempPathFactory, net_path: Path) -> Path:
    out = tmp_path_factory.mktemp("fsm")
    evaluate(
        out,
        net_path,
        "--baseline",
        "fsm_idm",
        "--scenarios",
        str(N_SCENARIOS),
        "--seed",
        "7",
        "--trajectories",
    )
    return out


@pytest.fixture(params=["idm", "fsm"])
def run_dir(request: pytest.FixtureRequest) -> Path:
    return request.getfixturevalue(f"{request.param}_run")


# --- the CSV contract -------------------------------------------------------------------------------


def test_design_columns_match_the_code() -> None:
    assert list(EPISODE_COLUMNS) == DESIGN_EPISODE_COLUMNS
    # The columns before issue #15 keep their names and places.
    assert list(EPISODE_COLUMNS[: len(BASE_EPISODE_COLUMNS)]) == list(BASE_EPISODE_COLUMNS)
    assert len(BASE_EPISODE_COLUMNS) == 17
    assert list(SUMMARY_COLUMNS) == DESIGN_SUMMARY_COLUMNS
    assert list(FLOW_COLUMNS) == DESIGN_FLOW_COLUMNS


@pytest.mark.sumo
def test_csvs_have_exactly_the_design_columns(run_dir: Path) -> None:
    assert header(run_dir / "episodes.csv") == DESIGN_EPISODE_COLUMNS
    assert header(run_dir / "summary.csv") == DESIGN_SUMMARY_COLUMNS
    assert header(run_dir / "flow.csv") == DESIGN_FLOW_COLUMNS


@pytest.mark.sumo
@pytest.mark.parametrize(("fixture", "method"), [("idm_run", "idm"), ("fsm_run", "fsm_idm")])
def test_one_row_per_scenario_and_method(request: pytest.FixtureRequest, fixture: str, method: str) -> None:
    out: Path = request.getfixturevalue(fixture)
    episodes = pd.read_csv(out / "episodes.csv")
    flow = pd.read_csv(out / "flow.csv")
    summary = pd.read_csv(out / "summary.csv")
    expected = [f"paper-{i:03d}" for i in range(N_SCENARIOS)]
    assert episodes["scenario"].tolist() == expected
    assert flow["scenario"].tolist() == expected
    assert set(episodes["method"]) == {method} == set(flow["method"])
    assert (episodes["seed"] == 7).all()
    assert summary["method"].tolist() == [method]
    assert summary["scenarios"].tolist() == [N_SCENARIOS]
    assert set(episodes["success"]) <= {0, 1} and set(episodes["perfect"]) <= {0, 1}
    assert (episodes["perfect"] <= episodes["success"]).all()
    assert set(episodes["ego_road"]) <= {"main", "merge"}
    assert episodes["ego_type"].between(-2.0, 2.0).all()
    assert (flow["vehicles"] >= 4).all()  # 2 to 8 vehicles per road


@pytest.mark.sumo
def test_no_temporary_files_are_left_behind(run_dir: Path) -> None:
    assert sorted(p.name for p in run_dir.iterdir()) == sorted(
        [*CSV_NAMES, "trajectories.csv", "settings.json", "replay", MANIFEST_NAME]
    )
    assert sorted(p.name for p in (run_dir / "replay").iterdir()) == [
        "net.net.xml",
        "run.json",
        "scenarios.jsonl",
    ]


# --- determinism ------------------------------------------------------------------------------------


@pytest.mark.sumo
def test_same_seed_gives_byte_identical_csvs(tmp_path: Path, net_path: Path, idm_run: Path) -> None:
    again = tmp_path / "again"
    evaluate(
        again, net_path, "--baseline", "idm", "--scenarios", str(N_SCENARIOS), "--seed", "7", "--trajectories"
    )
    for name in (*CSV_NAMES, "trajectories.csv"):
        assert (again / name).read_bytes() == (idm_run / name).read_bytes(), name


@pytest.mark.sumo
def test_different_seed_gives_different_episodes(tmp_path: Path, net_path: Path, idm_run: Path) -> None:
    other = tmp_path / "other"
    evaluate(other, net_path, "--baseline", "idm", "--scenarios", str(N_SCENARIOS), "--seed", "8")
    a = pd.read_csv(idm_run / "episodes.csv").drop(columns="seed")
    b = pd.read_csv(other / "episodes.csv").drop(columns="seed")
    assert not a.equals(b)
    assert (idm_run / "flow.csv").read_bytes() != (other / "flow.csv").read_bytes()


# --- numbers agree with the trajectories ------------------------------------------------------------


@pytest.mark.sumo
def test_flow_numbers_agree_with_trajectories(run_dir: Path) -> None:
    traj = pd.read_csv(run_dir / "trajectories.csv")
    flow = pd.read_csv(run_dir / "flow.csv").set_index("scenario")
    assert set(traj["scenario"]) == set(flow.index)
    for scenario, steps in traj.groupby("scenario"):
        row = flow.loc[scenario]
        duration = steps["time_s"].max() - steps["time_s"].min()
        crossed = steps[steps["dist_to_merge_m"] <= 0.0].groupby("vehicle")["time_s"].min()
        assert row["vehicles"] == steps["vehicle"].nunique()
        assert row["throughput_veh_per_h"] == pytest.approx(len(crossed) / duration * 3600.0, abs=1e-3)
        if len(crossed):
            assert row["merge_time_s"] == pytest.approx(crossed.max() - crossed.min(), abs=1e-3)
        assert row["mean_speed_mps"] == pytest.approx(steps["speed_mps"].mean(), abs=1e-4)


@pytest.mark.sumo
def test_episode_numbers_agree_with_trajectories(run_dir: Path) -> None:
    traj = pd.read_csv(run_dir / "trajectories.csv")
    episodes = pd.read_csv(run_dir / "episodes.csv")
    for ep in episodes.itertuples(index=False):
        steps = traj[traj["scenario"] == ep.scenario]
        ego = steps[steps["vehicle"] == ep.ego_id]
        assert len(ego), f"{ep.scenario}: ego {ep.ego_id} not in the trajectory"
        assert (ego["method"] == ep.method).all()
        assert set(ego["road"]) - {"out", "junction"} == {ep.ego_road}
        assert ep.ego_mean_speed_mps == pytest.approx(ego["speed_mps"].mean(), abs=1e-4)
        controlled = steps[steps["controlled"]]
        assert ep.mean_speed_mps == pytest.approx(controlled["speed_mps"].mean(), abs=1e-4)
        if ep.collisions > 0:
            assert ep.success == 0 and ep.perfect == 0
        if ep.success:
            assert np.isfinite(ep.ego_finish_time_s)
        # Travel and merge times are measured from the ego's entry, which is its first row.
        entry = ego["time_s"].min()
        crossed = ego[ego["dist_to_merge_m"] <= 0.0]["time_s"]
        if len(crossed):
            assert ep.ego_merge_time_s == pytest.approx(crossed.min() - entry, abs=1e-3)
            before = ego[ego["time_s"] < crossed.min()]
            assert ep.ego_merge_speed_mps == pytest.approx(before["speed_mps"].mean(), abs=1e-4)
        else:
            assert np.isnan(ep.ego_merge_time_s) and np.isnan(ep.ego_merge_speed_mps)
        if ep.ego_success:
            assert np.isfinite(ep.ego_travel_time_s) and ep.ego_travel_time_s <= ep.ego_finish_time_s + 1e-9


@pytest.mark.sumo
def test_summary_agrees_with_episodes(run_dir: Path) -> None:
    episodes = pd.read_csv(run_dir / "episodes.csv")
    summary = pd.read_csv(run_dir / "summary.csv").iloc[0]
    assert summary["success_pct"] == pytest.approx(100.0 * episodes["success"].mean(), abs=0.01)
    assert summary["perfect_pct"] == pytest.approx(100.0 * episodes["perfect"].mean(), abs=0.01)
    assert summary["perfect_no_flow_pct"] == pytest.approx(
        100.0 * episodes["perfect_no_flow"].mean(), abs=0.01
    )
    assert summary["collision_pct"] == pytest.approx(100.0 * (episodes["collisions"] > 0).mean(), abs=0.01)
    assert summary["timeout_pct"] == pytest.approx(100.0 * episodes["timeout"].mean(), abs=0.01)
    assert summary["ego_success_pct"] == pytest.approx(100.0 * episodes["ego_success"].mean(), abs=0.01)
    # Each relaxes or restricts success as its definition says.
    assert (episodes["perfect"] <= episodes["perfect_no_flow"]).all()
    assert (episodes["perfect_no_flow"] <= episodes["success"]).all()
    assert (episodes["success"] <= episodes["ego_success"]).all()
    perfect = episodes[episodes["perfect"] == 1]
    if len(perfect):
        assert summary["avg_speed_perfect_mps"] == pytest.approx(perfect["mean_speed_mps"].mean(), abs=1e-3)
    else:
        assert np.isnan(summary["avg_speed_perfect_mps"])


# --- suites -----------------------------------------------------------------------------------------


@pytest.mark.sumo
@pytest.mark.parametrize("method", ["idm", "fsm_idm"])
def test_representative_suite(tmp_path: Path, net_path: Path, method: str) -> None:
    evaluate(tmp_path / "r", net_path, "--baseline", method, "--suite", "representative")
    episodes = pd.read_csv(tmp_path / "r" / "episodes.csv")
    assert episodes["scenario"].tolist() == ["s1", "s2", "s3", "s4"]
    assert (episodes["method"] == method).all()
    assert (episodes["ego_road"] == "merge").all()
    assert pd.read_csv(tmp_path / "r" / "summary.csv")["scenarios"].tolist() == [4]


@pytest.mark.sumo
def test_driver_types_suite(tmp_path: Path, net_path: Path) -> None:
    evaluate(tmp_path / "d", net_path, "--baseline", "idm", "--suite", "driver-types", "--scenarios", "2")
    episodes = pd.read_csv(tmp_path / "d" / "episodes.csv")
    assert len(episodes) == 2 * 9  # two start offsets, nine driver types each
    np.testing.assert_allclose(episodes["ego_type"], np.tile(np.linspace(-2.0, 2.0, 9), 2))
    assert episodes["scenario"].is_unique
    assert episodes["scenario"].str.match(r"sweep0[01]-btype[+-]\d\.\d$").all()
    assert (episodes["ego_id"] == "merge_car").all() and (episodes["ego_road"] == "merge").all()
    # The normalisation divides by r_finish of the ego's own driver type.
    finish = (15.0 * episodes["ego_type"] + 50.0) / 4.0
    np.testing.assert_allclose(episodes["normalized_reward"], episodes["total_reward"] / finish, atol=1e-3)
    assert pd.read_csv(tmp_path / "d" / "summary.csv")["scenarios"].tolist() == [18]


@pytest.mark.sumo
def test_sumo_output_writes_tripinfo_xml(tmp_path: Path, net_path: Path) -> None:
    out = tmp_path / "s"
    evaluate(out, net_path, "--baseline", "idm", "--scenarios", "3", "--sumo-output")
    files = sorted((out / "sumo").glob("*.tripinfo.xml"))
    assert [f.name for f in files] == [f"idm-paper-{i:03d}.tripinfo.xml" for i in range(3)]
    flow = pd.read_csv(out / "flow.csv")
    for f, vehicles in zip(files, flow["vehicles"], strict=True):
        root = ET.parse(f).getroot()
        assert root.tag == "tripinfos"
        trips = root.findall("tripinfo")
        assert trips, f"{f.name}: no <tripinfo> entries"
        ids = {t.get("id") for t in trips}
        assert all(i and (i.startswith("main") or i.startswith("merge")) for i in ids)
        # Every vehicle of the episode is reported, also those still driving when the episode ended.
        assert len(ids) == vehicles, f"{f.name}: {len(ids)} tripinfos for {vehicles} vehicles"


# --- metric functions on a hand-built trajectory ----------------------------------------------------


def _trajectory() -> pd.DataFrame:
    """Two controlled vehicles and one SUMO car, steps of 1 s from t = 10 s.

    a (main):  dist 20, 5, -10, -52, -70 -> crosses the merge point at t = 12, finishes (-50 m) at t = 13
    b (merge): dist 30, 15, 2, -20, -50  -> crosses at t = 13, finishes at t = 14
    c (sumo):  stays 100 m before the merge point, never crosses
    """
    rows = []
    dists = {"a": [20, 5, -10, -52, -70], "b": [30, 15, 2, -20, -50], "c": [100] * 5}
    speeds = {"a": [15, 15, 16, 17, 18], "b": [10, 12, 14, 14, 16], "c": [0, 0, 0, 0, 0]}
    roads = {"a": "main", "b": "merge", "c": "main"}
    for k in range(5):
        for v in ("a", "b", "c"):
            rows.append(
                {
                    "time_s": 10.0 + k,
                    "vehicle": v,
                    "controlled": v != "c",
                    "method": {"a": "idm", "b": "others", "c": "sumo"}[v],
                    "road": roads[v] if dists[v][k] > 0 else "out",
                    "dist_to_merge_m": float(dists[v][k]),
                    "speed_mps": float(speeds[v][k]),
                    "accel_mps2": 0.0,
                    "action": 2 if v != "c" else -1,
                    "allowed_actions": "1111110" if v != "c" else "",
                }
            )
    return pd.DataFrame(rows)


def _facts(**overrides: object) -> EpisodeFacts:
    base = {
        "scenario": "hand",
        "seed": 3,
        "method": "idm",
        "ego_id": "a",
        "ego_road": "main",
        "ego_prio": 1,
        "ego_type": 2.0,
        "collisions": 0,
        "hard_brakes": 0,
        "hard_brakes_merge_zone": 0,
        "impedes": 0,
        "all_finished": True,
        "ego_total_reward": 10.0,
        "duration_s": 4.0,
        "start_time_s": 10.0,
        "free_flow_time_s": {"a": 2.5, "b": 3.0, "c": 9.0},
        "timed_out": False,
        "ego_end_reason": "finished",
    }
    base.update(overrides)
    return EpisodeFacts(**base)  # type: ignore[arg-type]


def test_merge_crossings_and_finish_times() -> None:
    traj = _trajectory()
    crossings = merge_crossings(traj)
    assert crossings["a"] == 12.0 and crossings["b"] == 13.0 and np.isnan(crossings["c"])
    finishes = finish_times(traj)
    assert finishes["a"] == 13.0 and finishes["b"] == 14.0 and np.isnan(finishes["c"])


def test_flow_row_hand_computed() -> None:
    row = flow_row(_trajectory(), _facts())
    assert list(row) == DESIGN_FLOW_COLUMNS
    assert row["vehicles"] == 3
    assert row["throughput_veh_per_h"] == pytest.approx(2 / 4.0 * 3600.0)  # 1800 veh/h
    assert row["merge_time_s"] == pytest.approx(1.0)  # 13 - 12
    assert row["mean_travel_time_s"] == pytest.approx((3.0 + 4.0) / 2)  # finished ones only
    assert row["mean_time_loss_s"] == pytest.approx(((3.0 - 2.5) + (4.0 - 3.0)) / 2)
    all_speeds = [15, 15, 16, 17, 18, 10, 12, 14, 14, 16, 0, 0, 0, 0, 0]
    assert row["mean_speed_mps"] == pytest.approx(np.mean(all_speeds), abs=1e-4)


def test_flow_row_without_crossings() -> None:
    traj = _trajectory()
    traj = traj[traj["time_s"] <= 11.0]  # nobody has reached the merge point yet
    row = flow_row(traj, _facts(duration_s=1.0))
    assert row["throughput_veh_per_h"] == 0.0
    assert np.isnan(row["merge_time_s"])
    assert np.isnan(row["mean_travel_time_s"]) and np.isnan(row["mean_time_loss_s"])


def test_episode_row_hand_computed() -> None:
    row = episode_row(_trajectory(), _facts())
    assert list(row) == DESIGN_EPISODE_COLUMNS
    assert row["success"] == 1 and row["perfect"] == 1
    assert row["ego_finish_time_s"] == pytest.approx(3.0)  # 13 - start 10
    assert row["ego_mean_speed_mps"] == pytest.approx(np.mean([15, 15, 16, 17, 18]))
    # Controlled vehicles only: the SUMO car does not count.
    assert row["mean_speed_mps"] == pytest.approx(np.mean([15, 15, 16, 17, 18, 10, 12, 14, 14, 16]))
    assert row["normalized_reward"] == pytest.approx(10.0 / ((15.0 * 2.0 + 50.0) / 4.0))
    assert (row["perfect_no_flow"], row["timeout"], row["ego_success"]) == (1, 0, 1)
    assert row["ego_travel_time_s"] == pytest.approx(3.0)  # on the road from t = 10, finished at 13
    assert row["ego_merge_time_s"] == pytest.approx(2.0)  # past the merge point at t = 12
    assert row["ego_merge_speed_mps"] == pytest.approx(15.0)  # its speeds at t = 10 and 11


def test_late_ego_times_from_its_entry() -> None:
    """b enters at t = 11, a second after the episode started: the finish time counts from the episode's
    start, travel and merge times from b's entry."""
    traj = _trajectory()
    traj = traj[~((traj["vehicle"] == "b") & (traj["time_s"] < 11.0))]
    row = episode_row(traj, _facts(ego_id="b", ego_road="merge"))
    assert row["ego_finish_time_s"] == pytest.approx(4.0)  # 14 - start 10
    assert row["ego_travel_time_s"] == pytest.approx(3.0)  # 14 - entry 11
    assert row["ego_merge_time_s"] == pytest.approx(2.0)  # 13 - entry 11
    assert row["ego_merge_speed_mps"] == pytest.approx(np.mean([12, 14]))  # t = 11, 12


@pytest.mark.parametrize(
    ("overrides", "success", "perfect", "perfect_no_flow"),
    [
        ({"collisions": 1}, 0, 0, 0),
        ({"all_finished": False}, 0, 0, 0),
        ({"impedes": 1}, 1, 0, 0),
        ({"hard_brakes_merge_zone": 2, "hard_brakes": 2}, 1, 0, 1),  # only the flow penalty
        ({"hard_brakes": 3}, 1, 1, 1),  # hard brakes outside the merging zone cost no reward
        ({"hard_brakes_merge_zone": 1, "hard_brakes": 1, "impedes": 2}, 1, 0, 0),
    ],
)
def test_success_and_perfect(
    overrides: dict[str, object], success: int, perfect: int, perfect_no_flow: int
) -> None:
    row = episode_row(_trajectory(), _facts(**overrides))
    assert (row["success"], row["perfect"], row["perfect_no_flow"]) == (success, perfect, perfect_no_flow)


@pytest.mark.parametrize(
    ("overrides", "timeout", "ego_success"),
    [
        ({"timed_out": True, "all_finished": False, "ego_end_reason": "timeout"}, 1, 0),
        # The ego finished, another car did not: a timeout, and the ego's own success.
        ({"timed_out": True, "all_finished": False, "ego_end_reason": "finished"}, 1, 1),
        # Everyone finished in the last step: no timeout.
        ({"timed_out": True, "all_finished": True}, 0, 1),
        # Ended by a collision before the time limit.
        ({"collisions": 1, "all_finished": False, "ego_end_reason": "collided"}, 0, 0),
        ({"collisions": 1, "all_finished": False, "ego_end_reason": "finished"}, 0, 1),
        # An ego that never entered has no end reason.
        ({"timed_out": True, "all_finished": False, "ego_end_reason": ""}, 1, 0),
    ],
)
def test_timeout_and_ego_success(overrides: dict[str, object], timeout: int, ego_success: int) -> None:
    row = episode_row(_trajectory(), _facts(**overrides))
    assert (row["timeout"], row["ego_success"]) == (timeout, ego_success)


def test_ego_that_never_finishes_has_no_finish_time() -> None:
    row = episode_row(_trajectory(), _facts(ego_id="c", all_finished=False))
    assert np.isnan(row["ego_finish_time_s"])


def test_summary_rows_hand_computed() -> None:
    episodes = pd.DataFrame(
        {
            "method": ["idm", "idm", "idm", "idm", "fsm_idm"],
            "success": [1, 1, 0, 1, 0],
            "perfect": [1, 0, 0, 1, 0],
            "mean_speed_mps": [10.0, 99.0, 99.0, 14.0, 5.0],
            "perfect_no_flow": [1, 1, 0, 1, 0],
            "collisions": [0, 0, 2, 0, 1],
            "timeout": [0, 0, 1, 0, 0],
            "ego_success": [1, 1, 1, 1, 0],
        }
    )
    rows = summary_rows(episodes)
    assert [r["method"] for r in rows] == ["idm", "fsm_idm"]  # order of first appearance
    idm, fsm = rows
    assert idm == {
        "method": "idm",
        "scenarios": 4,
        "success_pct": 75.0,
        "perfect_pct": 50.0,
        "avg_speed_perfect_mps": 12.0,
        "perfect_no_flow_pct": 75.0,
        "collision_pct": 25.0,  # scenarios with a collision, not collisions
        "timeout_pct": 25.0,
        "ego_success_pct": 100.0,
    }
    assert list(idm) == DESIGN_SUMMARY_COLUMNS
    assert fsm["success_pct"] == 0.0 and np.isnan(fsm["avg_speed_perfect_mps"])
    assert (fsm["collision_pct"], fsm["ego_success_pct"]) == (100.0, 0.0)


@pytest.mark.sumo
def test_outputs_get_the_usual_file_permissions(tmp_path: Path, net_path: Path) -> None:
    """Results are shared files: the atomic write must not leave them owner-only (mkstemp's 0600)."""
    import os

    umask = os.umask(0o022)
    try:
        evaluate(tmp_path / "p", net_path, "--baseline", "idm", "--scenarios", "3")
    finally:
        os.umask(umask)
    for name in CSV_NAMES:
        assert (tmp_path / "p" / name).stat().st_mode & 0o777 == 0o644, name


@pytest.mark.sumo
def test_scenario_files_are_evaluated_with_their_first_vehicle_as_ego(tmp_path: Path, net_path: Path) -> None:
    s4 = shipped("scenarios/representative/s4.toml")
    evaluate(tmp_path / "f", net_path, "--baseline", "idm", "--scenario", str(s4), "--scenario", str(s4))
    episodes = pd.read_csv(tmp_path / "f" / "episodes.csv")
    assert episodes["scenario"].tolist() == ["s4", "s4"]
    assert (episodes["ego_id"] == "main_car").all()  # the file's first vehicle


@pytest.mark.sumo
def test_config_changes_the_paper_suite_traffic(tmp_path: Path, net_path: Path) -> None:
    config = tmp_path / "eval.toml"
    config.write_text(
        "max_episode_s = 30.0\n[traffic]\nn_vehicles = 0\nmin_vehicles_per_road = 2\nmax_vehicles_per_road = 2\n"
    )
    evaluate(tmp_path / "c", net_path, "--baseline", "idm", "--scenarios", "3", "--config", str(config))
    flow = pd.read_csv(tmp_path / "c" / "flow.csv")
    assert (flow["vehicles"] == 4).all()  # 2 per road, as configured


def test_bad_eval_config_is_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "eval.toml"
    config.write_text("max_episode_s = 60\n[trafic]\n")
    assert main(["evaluate", "--baseline", "idm", "--config", str(config), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'did you mean "traffic"' in err[0]
    assert not (tmp_path / "o").exists()


def test_fsm_rules_drive_the_ego_only_in_a_case_every_other_method_drives_whole() -> None:
    """As the paper runs FSM+IDM (it has no driver type) on one car of the representative scenes, so its smooth
    twin of ours; IDM and the learned methods drive every car the case gives them."""
    from idas_sumo.env.scenario import Scenario, VehicleSpec
    from idas_sumo.evaluation.protocol import EvalCase, eval_jobs

    scenario = Scenario("two", (VehicleSpec("a", "main", 20.0, 10.0), VehicleSpec("b", "merge", 20.0, 10.0)))
    case = EvalCase(scenario, "a", 0, ("a", "b"))
    jobs = eval_jobs([case], ["idm", "fsm_idm", "fsm_idm_smooth", "idas"])
    assert {j.method: j.case.method_vehicles for j in jobs} == {
        "idm": ("a", "b"),
        "fsm_idm": ("a",),
        "fsm_idm_smooth": ("a",),
        "idas": ("a", "b"),
    }


def test_paired_margin_by_hand() -> None:
    from idas_sumo.evaluation.metrics import paired_margin

    # Two seeds, four shared scenarios; IDM also ran a fifth that IDAS did not (left out of the pairing).
    rows = [
        ("idas", 1, "a", 1),
        ("idas", 1, "b", 1),
        ("idas", 2, "a", 0),
        ("idas", 2, "b", 1),
        ("idm", 1, "a", 0),
        ("idm", 1, "b", 1),
        ("idm", 2, "a", 0),
        ("idm", 2, "b", 0),
        ("idm", 2, "c", 1),
    ]
    episodes = pd.DataFrame(rows, columns=["method", "seed", "scenario", "perfect"])
    m = paired_margin(episodes, "idas", "idm")
    # Differences 1, 0, 0, 1: mean 0.5; sample sd sqrt(1/3) = 0.57735; / sqrt(4) = 0.288675.
    assert (m.margin_pts, m.standard_error_pts, m.scenarios) == (50.0, 28.87, 4)
    assert paired_margin(episodes, "idm", "idas").margin_pts == -50.0
    with pytest.raises(ValueError, match="share 0 scenarios"):
        paired_margin(episodes, "idas", "fsm_idm")


@pytest.mark.sumo
def test_others_policy_replaces_the_others_file_in_process_and_in_workers(
    tmp_path: Path, net_path: Path
) -> None:
    """``--others idas --others-policy F`` runs the other cars on F: the same episodes as ``--others idas_v`` when F
    is the shipped ``idas_v.pt``, in this process and in two workers alike; the replay record and the settings name
    F, so that a replay loads the very weights the others ran."""
    import json

    by_name, by_file = tmp_path / "by_name", tmp_path / "by_file"
    assert main(evaluate_args(by_name, net_path, "--scenarios", "3", "--others", "idas_v")) == 0
    idas_v = shipped("policies/idas_v.pt")
    others_policy = ["--others", "idas", "--others-policy", str(idas_v), "--workers", "2"]
    assert main(evaluate_args(by_file, net_path, "--scenarios", "3", *others_policy)) == 0
    for name in CSV_NAMES:
        a, b = pd.read_csv(by_name / name), pd.read_csv(by_file / name)
        pd.testing.assert_frame_equal(a, b)
    record = json.loads((by_file / "replay" / "run.json").read_text())["others"]
    assert (record["method"], Path(record["path"])) == ("idas", idas_v.resolve())
    assert json.loads((by_file / "settings.json").read_text())["others_policy"] == str(idas_v)


def test_others_policy_for_rule_based_others_is_refused(
    tmp_path: Path, net_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = evaluate_args(tmp_path / "out", net_path, "--others", "idm")
    assert main([*args, "--others-policy", str(shipped("policies/idas.pt"))]) == 2
    err = capsys.readouterr().err
    assert "--others-policy" in err and "idm" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()
