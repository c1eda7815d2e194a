"""PNG plots: written by `evaluate --plots` and by `idas-sumo plot`; a directory without results is exit 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from idas_sumo.cli import main
from idas_sumo.io_utils import MANIFEST_NAME

REPO_ROOT = Path(__file__).resolve().parents[1]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def assert_png(path: Path) -> None:
    assert path.is_file(), f"{path.name} missing"
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, f"{path.name} is not a PNG"
    assert len(data) > 5_000, f"{path.name} is suspiciously small ({len(data)} bytes)"


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "idas_sumo.cli", *args],
        capture_output=True,
        text=True,
        cwd=REPO_ROOT,
        timeout=60,
    )


def evaluate(out: Path, net: Path, *extra: str) -> None:
    args = ["evaluate", "--net", str(net), "--out", str(out), "--others", "idm", "--no-progress", *extra]
    assert main(args) == 0


@pytest.fixture(scope="module")
def representative(tmp_path_factory: pytest.TempPathFactory, net_path: Path) -> Path:
    out = tmp_path_factory.mktemp("rep") / "out"
    evaluate(out, net_path, "--baseline", "idm", "--suite", "representative", "--trajectories", "--plots")
    return out


@pytest.mark.sumo
def test_evaluate_plots_writes_pngs(representative: Path) -> None:
    for name in ("summary.png", "representative.png", "profiles.png"):
        assert_png(representative / name)
    left = [p.name for p in representative.iterdir() if p.name.startswith(".") or p.suffix == ".tmp"]
    assert left == [MANIFEST_NAME]  # what the folder's files are: the tool's, the PNGs among them
    assert {"summary.png", "profiles.png"} <= set((representative / MANIFEST_NAME).read_text().split())


@pytest.mark.sumo
def test_plot_command_redraws_from_the_csvs(representative: Path) -> None:
    before = {p.name for p in representative.glob("*.png")}
    for png in representative.glob("*.png"):
        png.unlink()
    result = run_cli("plot", str(representative))
    assert result.returncode == 0, result.stderr
    after = {p.name for p in representative.glob("*.png")}
    assert after == before
    for name in after:
        assert_png(representative / name)
        assert name in result.stdout


@pytest.mark.sumo
def test_driver_type_sweep_plot(tmp_path: Path, net_path: Path) -> None:
    out = tmp_path / "sweep"
    evaluate(out, net_path, "--baseline", "idm", "--suite", "driver-types", "--trajectories", "--plots")
    assert_png(out / "summary.png")
    assert_png(out / "driver_types.png")


@pytest.mark.sumo
def test_paper_suite_without_trajectories_plots_the_summary_and_the_flow(
    tmp_path: Path, net_path: Path
) -> None:
    out = tmp_path / "paper"
    evaluate(out, net_path, "--baseline", "idm", "--scenarios", "3", "--plots")
    assert sorted(p.name for p in out.glob("*.png")) == ["flow.png", "summary.png"]
    assert_png(out / "summary.png")
    assert_png(out / "flow.png")


def _assert_one_line_exit_2(result: subprocess.CompletedProcess[str], needle: str) -> None:
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("idas-sumo: error:") and needle in lines[0], lines[0]


def test_plot_on_a_directory_without_episodes(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("nothing here\n")
    result = run_cli("plot", str(tmp_path))
    _assert_one_line_exit_2(result, "episodes.csv")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_plot_on_a_missing_directory(tmp_path: Path) -> None:
    _assert_one_line_exit_2(run_cli("plot", str(tmp_path / "nope")), str(tmp_path / "nope"))


def test_plot_on_a_broken_episodes_csv(tmp_path: Path) -> None:
    (tmp_path / "episodes.csv").write_text("")
    _assert_one_line_exit_2(run_cli("plot", str(tmp_path)), "episodes.csv")


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("episodes.csv", "a,b\n1,2\n"),  # a CSV, but not ours
        ("trajectories.csv", "x,y\n1,2\n"),
    ],
)
def test_plot_on_csvs_with_the_wrong_columns(tmp_path: Path, name: str, text: str) -> None:
    if name != "episodes.csv":
        header = "scenario,seed,method,ego_id,ego_road,ego_prio,ego_type,success,perfect,collisions,"
        header += "hard_brakes,hard_brakes_merge_zone,ego_finish_time_s,ego_mean_speed_mps,mean_speed_mps,"
        header += "total_reward,normalized_reward\n"
        row = "s1,0,idm,merge_car,merge,0,1.0,1,1,0,0,0,10.0,14.0,14.0,20.0,1.0\n"
        (tmp_path / "episodes.csv").write_text(header + row)
    (tmp_path / name).write_text(text)
    _assert_one_line_exit_2(run_cli("plot", str(tmp_path)), name)
