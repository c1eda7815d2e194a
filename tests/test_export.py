"""`idas-sumo export`: a scenario file, or an evaluated episode, as .sumocfg + .rou.xml + net that plain
`sumo` runs (exit 0, every car's trip, each departing as the scenario says), moved away from idas-sumo;
bad input is one line and exit 2, and nothing of the user's is touched."""

from __future__ import annotations

import shutil
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import sumo  # the eclipse-sumo wheel: its plain `sumo` binary, not libsumo

from idas_sumo.cli import main
from idas_sumo.env.scenario import Scenario, load_scenario
from idas_sumo.evaluation.replay import load_replay_data
from idas_sumo.io_utils import PACKAGE_DIR
from idas_sumo.resources import SCENARIO_DIR
from idas_sumo.sim.backend import run_options
from idas_sumo.sim.plain_sumo import sumocfg_xml

SUMO = Path(sumo.SUMO_HOME) / "bin" / "sumo"
S1 = SCENARIO_DIR / "representative" / "s1.toml"
REPLAY_BASE = Path(__file__).parent / "data" / "replay_base"
"""A stored evaluation (IDM among IDM others, two scenarios of eight cars)."""


def run_plain_sumo(exported: Path, elsewhere: Path) -> dict[str, dict[str, str]]:
    """Move the exported folder, run its .sumocfg in plain `sumo` with an empty environment (no
    SUMO_HOME, no Python path); each trip's tripinfo attributes by vehicle id."""
    shutil.copytree(exported, elsewhere)
    (config,) = elsewhere.glob("*.sumocfg")
    run = subprocess.run(
        [str(SUMO), "-c", config.name, "--tripinfo-output", "trips.xml"],
        cwd=elsewhere,
        env={},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 0, run.stderr
    return {t.attrib["id"]: t.attrib for t in ET.parse(elsewhere / "trips.xml").getroot()}


def assert_departs_as_scenario(trips: dict[str, dict[str, str]], scenario: Scenario) -> None:
    assert sorted(trips) == sorted(v.id for v in scenario.vehicles)
    for v in scenario.vehicles:
        trip = trips[v.id]
        assert float(trip["depart"]) == pytest.approx(v.depart_s)
        assert float(trip["departSpeed"]) == pytest.approx(v.speed_mps, abs=0.01)
        assert trip["departLane"].startswith(v.road)  # the T-junction's roads are its edges
        assert float(trip["arrival"]) > float(trip["depart"])  # drove through the merge and left


@pytest.mark.sumo
def test_an_exported_scenario_file_runs_in_plain_sumo(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "s1"
    assert main(["export", str(S1), "--out", str(out)]) == 0
    assert "sumo -c" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "s1.rou.xml",
        "s1.sumocfg",
        "tjunction.net.xml",
    ]
    routes = (out / "s1.rou.xml").read_text(encoding="utf-8")
    assert "SUMO drives every car here" in routes  # said where a SUMO user looks
    scenario = load_scenario(S1)
    trips = run_plain_sumo(out, tmp_path / "moved")
    assert_departs_as_scenario(trips, scenario)
    for v in scenario.vehicles:  # start positions as the engine places them (one-edge roads here)
        assert float(trips[v.id]["departPos"]) == pytest.approx(v.start_pos_m, abs=0.01)


@pytest.mark.sumo
def test_an_evaluated_episode_runs_in_plain_sumo(tmp_path: Path) -> None:
    out = tmp_path / "episode"
    assert main(["export", str(REPLAY_BASE), "--scenario", "paper-000", "--out", str(out)]) == 0
    data = load_replay_data(REPLAY_BASE)
    case = data.cases[0]
    assert any(v.depart_s > 0 for v in case.scenario.vehicles)  # later entries too
    config = ET.parse(out / "paper-000.sumocfg").getroot()
    assert config.find("random_number/seed").attrib["value"] == str(data.seed)  # type: ignore[union-attr]
    assert_departs_as_scenario(run_plain_sumo(out, tmp_path / "moved"), case.scenario)


def test_the_sumocfg_holds_the_engines_options() -> None:
    root = ET.fromstring(sumocfg_xml("n.net.xml", "r.rou.xml", seed=7))
    options = {el.tag: el.attrib["value"] for section in root for el in section}
    expected = run_options(7)
    assert options == {
        "net-file": "n.net.xml",
        "route-files": "r.rou.xml",
        **{f.removeprefix("--"): v for f, v in zip(expected[::2], expected[1::2], strict=True)},
    }


def one_line(capsys: pytest.CaptureFixture[str], *needles: str) -> None:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("idas-sumo: error:"), err
    for needle in needles:
        assert needle in err, err


@pytest.mark.sumo
@pytest.mark.parametrize(
    ("source", "extra", "needles"),
    [
        ("missing.toml", [], ["missing.toml: no such file or directory"]),
        (str(REPLAY_BASE), ["--scenario", "2"], ["--scenario 2", "index 0-1"]),
        (str(REPLAY_BASE), [], ["holds 2 scenarios", "--scenario"]),
        (str(REPLAY_BASE), ["--scenario", "0", "--net", str(S1)], ["--net", "leave out --net"]),
        (str(S1), ["--scenario", "0"], ["--scenario", "scenario file"]),
    ],
)
def test_bad_export_requests(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], source: str, extra: list[str], needles: list[str]
) -> None:
    out = tmp_path / "out"
    assert main(["export", source, *extra, "--out", str(out)]) == 2
    one_line(capsys, *needles)
    assert not out.exists()  # refused before anything was written


@pytest.mark.sumo
def test_a_non_empty_out_needs_force_and_keeps_the_users_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine\n")
    assert main(["export", str(S1), "--out", str(out)]) == 2
    one_line(capsys, "not empty", "--force")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert main(["export", str(S1), "--out", str(out), "--force"]) == 0
    assert (out / "notes.txt").read_text() == "mine\n" and (out / "s1.sumocfg").is_file()


@pytest.mark.sumo
def test_export_never_writes_into_the_installed_package(capsys: pytest.CaptureFixture[str]) -> None:
    target = PACKAGE_DIR / "scenarios" / "exported-by-a-test"
    assert main(["export", str(S1), "--out", str(target), "--force"]) == 2
    one_line(capsys, "installed idas_sumo package")
    assert not target.exists()
