"""``idas-sumo cosim``: SUMO flows with a share of automated cars, flow statistics, the resumable grid."""

from __future__ import annotations

import csv
import re
import shutil
from pathlib import Path

import pytest

from idas_sumo.baselines.policies import RuleBasedPolicy
from idas_sumo.cosim import study
from idas_sumo.cosim.demand import parse_demand, parse_penetrations, parse_profile
from idas_sumo.cosim.run import run_once
from idas_sumo.errors import InputError
from idas_sumo.io_utils import is_matplotlib_png
from idas_sumo.sim.flows import (
    ADDITIONAL_NAME,
    AUTOMATED_TYPE,
    CONFIG_NAME,
    OUTPUT_NAMES,
    ROUTE_NAME,
    FlowDemand,
    demand_xml,
    run_plain_sumo,
)
from idas_sumo.sim.merge_detect import MergeSite, as_site
from tests.conftest import main_in_process

MODERATE = {"main": 600.0, "merge": 200.0}
"""Well below the T-junction's capacity: every car gets through."""


@pytest.fixture(scope="module")
def site(net_path: Path) -> MergeSite:
    return as_site(net_path)


def _body(path: Path) -> list[str]:
    """An output file's lines after SUMO's header comment, without its wall-clock figures."""
    text = path.read_text()
    return [ln for ln in text[text.index("-->") :].splitlines() if "clockBegin" not in ln]


def test_demand_file_at_p0_is_plain_sumo_demand(site: MergeSite) -> None:
    plain = demand_xml(site, FlowDemand(MODERATE, 0.0, 60, 0, 60))
    assert AUTOMATED_TYPE not in plain and "vTypeDistribution" not in plain
    assert re.findall(r'<flow id="(\w+)" type="human"', plain) == ["main", "merge"]
    mixed = demand_xml(site, FlowDemand(MODERATE, 0.25, 60, 0, 60))
    assert 'probability="0.25"' in mixed and 'probability="0.75"' in mixed
    assert 'vehsPerHour="600.0"' in mixed and 'departLane="best"' in mixed


@pytest.mark.sumo
def test_p0_equals_plain_sumo(site: MergeSite, tmp_path: Path) -> None:
    """With no automated car the run's loop commands nothing: every SUMO output equals the sumo binary's."""
    ours, plain = tmp_path / "ours", tmp_path / "plain"
    demand = FlowDemand({"main": 1200.0, "merge": 400.0}, 0.0, 180.0, 3, 60.0)
    result = run_once(site, demand, None, ours)
    plain.mkdir()
    for name in (CONFIG_NAME, ROUTE_NAME, ADDITIONAL_NAME):
        shutil.copy(ours / name, plain / name)
    run_plain_sumo(plain / CONFIG_NAME, timeout_s=60)
    for name in OUTPUT_NAMES.values():
        assert _body(ours / name) == _body(plain / name), name
    assert result.row["inserted"] > 50 and result.row["automated"] == 0
    # a congested merge road (time loss) and the engine's own count of cars past the merge agrees with SUMO's loop
    assert result.row["merge_mean_time_loss_s"] > 10.0
    assert (
        abs(result.row["engine_throughput_veh_per_h"] - result.row["throughput_veh_per_h"]) <= 3600 / 180 * 2
    )
    assert len(result.bins) == 3 and sum(b["arrived"] for b in result.bins) == result.row["arrived"]


@pytest.mark.sumo
@pytest.mark.parametrize("method", ["idm", "idas"])
def test_every_car_automated_moderate_demand(site: MergeSite, tmp_path: Path, method: str) -> None:
    from idas_sumo.evaluation.policies import resolve_policy

    policy = RuleBasedPolicy("idm") if method == "idm" else resolve_policy("idas")
    demand = FlowDemand(MODERATE, 1.0, 180.0, 0, 180.0)
    row = run_once(site, demand, policy, tmp_path / method).row
    assert row["automated"] == row["inserted"] > 25
    assert row["collisions"] == 0 and row["teleports"] == 0
    assert row["arrived"] >= row["inserted"] - 12  # the last ~20 s of cars are still on the road
    plain = run_once(site, FlowDemand(MODERATE, 0.0, 180.0, 0, 180.0), None, tmp_path / "plain").row
    assert row["mean_travel_time_s"] != plain["mean_travel_time_s"]  # the policy, not SUMO, drove


@pytest.mark.sumo
def test_collisions_are_counted_as_sumo_counts_them(site: MergeSite, tmp_path: Path) -> None:
    """IDM never sees the other road's cars (the paper's IDM collides too): at this demand automated
    merge cars run into main-road cars. The loop's per-step count is SUMO's own total, and a warm-up
    leaves out the first bin's."""
    demand = FlowDemand({"main": 1200.0, "merge": 400.0}, 1.0, 120.0, 0, 60.0)
    result = run_once(site, demand, RuleBasedPolicy("idm"), tmp_path, warmup_s=60.0)
    row, bins = result.row, result.bins
    assert bins[0]["collisions"] > 0 and bins[1]["collisions"] > 0
    assert bins[0]["collisions"] + bins[1]["collisions"] == row["sumo_collisions_total"]
    assert row["collisions"] == bins[1]["collisions"] and row["geometric_collisions"] == 0
    assert row["throughput_veh_per_h"] == bins[1]["throughput_veh_per_h"]
    assert row["collisions_between_automated"] == row["collisions"]  # SUMO's collision output: who hit whom
    assert row["collisions_automated_human"] == row["collisions_between_human"] == 0


def test_bad_demand_and_penetration(site: MergeSite) -> None:
    assert parse_demand("main=1200, merge=0", site) == {"main": 1200.0, "merge": 0.0}
    for text in ("main=-1", "main=1e9", "main=nan", "main", "lane=100", "main=1,main=2", "main=0"):
        with pytest.raises(InputError):
            parse_demand(text, site)
    assert parse_penetrations("0,0.25,1") == [0.0, 0.25, 1.0]
    for text in ("-0.1", "1.01", "x", "0.5,0.5"):
        with pytest.raises(InputError):
            parse_penetrations(text)


@pytest.mark.sumo
@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--demand", "main=-100"], "--demand: main=-100"),
        (["--demand", "main=50000"], "--demand: main=50000"),
        (["--demand", "ramp=100"], "no road 'ramp'"),
        (["--demand", "main=100", "--penetration", "1.5"], "outside [0, 1]"),
        (["--demand", "main=100", "--duration-s", "0"], "--duration-s"),
        (["--demand", "main=100", "--duration-s", "300", "--bin-s", "70"], "--bin-s"),
        (["--demand", "main=100", "--duration-s", "300", "--warmup-s", "300"], "--warmup-s"),
        (["--demand", "main=100", "--policy", "idsa"], "--policy"),
        (["--demand", "main=100", "--net", "STRAIGHT"], "no merge"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, flags: list[str], message: str
) -> None:
    if "STRAIGHT" in flags:
        from idas_sumo.sim.sample_nets import build_sample_net

        flags[flags.index("STRAIGHT")] = str(build_sample_net("straight", tmp_path / "straight.net.xml"))
    args = ["--penetration", "0", *flags] if "--penetration" not in flags else flags
    out = tmp_path / "out"
    code, _, err = main_in_process(capsys, "cosim", *args, "--out", str(out))
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("idas-sumo: error: ") and message in err
    assert not out.exists()


@pytest.mark.sumo
def test_resume_skips_finished_runs(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "study"
    base = ["cosim", "--demand", "main=600,merge=200", "--penetration", "0", "--duration-s", "60"]
    ran: list[int] = []
    real = study.run_once

    def counting(site, flow, policy, folder, mask, warmup_s, **kw):  # type: ignore[no-untyped-def]
        if flow.seed == 1 and not ran.count(1):
            ran.append(1)
            raise KeyboardInterrupt  # the study is stopped during its second run
        ran.append(flow.seed)
        return real(site, flow, policy, folder, mask, warmup_s, **kw)

    monkeypatch.setattr(study, "run_once", counting)
    code, _, _ = main_in_process(capsys, *base, "--seeds", "0-2", "--out", str(out))
    assert code == 130 and ran == [0, 1]
    first = (out / "flows.csv").read_text().splitlines()
    assert len(first) == 2  # header and the one finished run
    code, stdout, err = main_in_process(capsys, *base, "--seeds", "0-2", "--out", str(out))
    assert code == 0, err
    assert ran == [0, 1, 1, 2] and "seed 0: done before, skipped" in stdout
    rows = list(csv.DictReader((out / "flows.csv").open()))
    assert [r["seed"] for r in rows] == ["0", "1", "2"]
    assert (out / "flows.csv").read_text().splitlines()[:2] == first  # the finished run kept as it was
    bins = list(csv.DictReader((out / "bins.csv").open()))
    assert [b["seed"] for b in bins] == ["0", "1", "2"]
    for column in (
        "throughput_veh_per_h",
        "mean_travel_time_s",
        "mean_time_loss_s",
        "collisions",
        "teleports",
    ):
        assert column in rows[0]
    assert is_matplotlib_png(out / "flows.png")


def test_output_folder_policy(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """A folder holding other files is reused only with --force; nothing is written into the package."""
    from idas_sumo.io_utils import PACKAGE_DIR

    base = ["cosim", "--demand", "main=600", "--penetration", "0", "--duration-s", "10"]
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    code, _, err = main_in_process(capsys, *base, "--out", str(mine))
    assert code == 2 and "--force" in err and not (mine / "flows.csv").exists()
    target = PACKAGE_DIR / "policies" / "written-by-a-test"
    code, _, err = main_in_process(capsys, *base, "--out", str(target))
    assert code == 2 and "installed idas_sumo package" in err and not target.exists()


@pytest.mark.sumo
def test_onramp_automated_cars_keep_to_the_merge_lanes(tmp_path: Path) -> None:
    """On a two-lane highway only the merge's lanes are the automated cars' world: cars side by side on
    the two lanes are no collision (before, the geometric check removed them: dozens per 300 s)."""
    from idas_sumo.sim.sample_nets import build_sample_net

    site = as_site(build_sample_net("onramp", tmp_path / "onramp.net.xml"))
    demand = FlowDemand({"main": 2400.0, "merge": 600.0}, 1.0, 90.0, 0, 90.0)
    row = run_once(site, demand, RuleBasedPolicy("idm"), tmp_path / "run").row
    assert row["automated"] == row["inserted"] > 60
    assert row["collisions"] == 0 and row["geometric_collisions"] == 0
    assert row["throughput_veh_per_h"] > 0
    # the roads can be named by their edges too
    assert parse_demand("hw_in=2400,ramp=600", site) == {"main": 2400.0, "merge": 600.0}


TIMING_COLUMNS = ("wall_s", "real_time_factor")


def _rows_without_timing(path: Path) -> list[dict[str, str]]:
    return [{k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in csv.DictReader(path.open())]


@pytest.mark.sumo
def test_workers_give_the_same_rows_and_resume(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """Two worker processes write the rows one process writes, in the same order; a second call with
    workers skips every finished run; --trajectories writes each run's positions for the plot."""
    grid = ["--demand", "main=900,merge=300", "--penetration", "0,0.5", "--policy", "idm"]
    base = ["cosim", *grid, "--duration-s", "30", "--seeds", "0"]
    one, two = tmp_path / "one", tmp_path / "two"
    code, _, err = main_in_process(capsys, *base, "--out", str(one))
    assert code == 0, err
    code, _, err = main_in_process(capsys, *base, "--workers", "2", "--trajectories", "--out", str(two))
    assert code == 0, err
    rows = _rows_without_timing(one / "flows.csv")
    assert len(rows) == 2 and rows == _rows_without_timing(two / "flows.csv")
    assert [r["penetration"] for r in rows] == ["0", "0.5"] and int(rows[1]["automated"]) > 0
    code, stdout, err = main_in_process(capsys, *base, "--workers", "2", "--out", str(two))
    assert code == 0 and stdout.count("done before, skipped") == 2, err
    traj = sorted((two / study.TRAJECTORY_DIR).glob("*.csv"))
    assert len(traj) == 2 and "p0.5" in traj[0].name
    cars = list(csv.DictReader(traj[0].open()))
    assert {c["road"] for c in cars} >= {"main", "merge"} and {c["automated"] for c in cars} == {"0", "1"}
    assert all(float(c["time_s"]).is_integer() for c in cars)
    code, stdout, err = main_in_process(capsys, "plot", str(two))
    assert code == 0, err
    assert is_matplotlib_png(two / "flows.png") and is_matplotlib_png(traj[0].with_suffix(".png"))
    assert stdout.count("wrote ") == 3


def test_demand_profile_makes_consecutive_flows(site: MergeSite, tmp_path: Path) -> None:
    profile_csv = tmp_path / "profile.csv"
    profile_csv.write_text("time_s,multiplier\n0,0.5\n60,1.5\n120,0\n")
    profile = parse_profile(profile_csv, 150.0)
    assert profile == ((0.0, 0.5), (60.0, 1.5), (120.0, 0.0))
    xml = demand_xml(site, FlowDemand(MODERATE, 0.0, 150.0, 0, 30.0, profile))
    flows = re.findall(r'<flow id="([\w.]+)" .*?begin="([\d.]+)" end="([\d.]+)" vehsPerHour="([\d.]+)"', xml)
    assert flows == [
        ("main.0", "0", "60", "300.0"),
        ("main.1", "60", "120", "900.0"),
        ("merge.0", "0", "60", "100.0"),
        ("merge.1", "60", "120", "300.0"),
    ]
    # without a profile the file is the one it always was (one flow per road, named after it)
    assert demand_xml(site, FlowDemand(MODERATE, 0.0, 150.0, 0, 30.0)).count("<flow ") == 2


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        ("time_s,multiplier\n10,1\n", "times start at 0"),
        ("time_s,multiplier\n0,1\n60,1\n30,2\n", "line 4: times start at 0 and increase"),
        ("time_s,multiplier\n0,-1\n", "multiplier in [0, 10]"),
        ("time_s,multiplier\n0,x\n", "two numbers"),
        ("time,mult\n0,1\n", "header time_s,multiplier"),
        ("time_s,multiplier\n0,1\n600,1\n", "not before the end"),
        ("time_s,multiplier\n0,6\n", "more than 3600 vehicles per hour"),
    ],
)
def test_bad_demand_profile_is_one_line_and_exit_2(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, rows: str, message: str
) -> None:
    profile_csv = tmp_path / "profile.csv"
    profile_csv.write_text(rows)
    out = tmp_path / "out"
    args = ["--demand", "main=900", "--penetration", "0", "--duration-s", "600", "--out", str(out)]
    code, _, err = main_in_process(capsys, "cosim", *args, "--demand-profile", str(profile_csv))
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("idas-sumo: error: --demand-profile") and message in err
    assert not out.exists()
