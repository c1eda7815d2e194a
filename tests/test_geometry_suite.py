"""``evaluate --suite geometry``: the paper suite on held-out generated merges and the on-ramp net."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import pytest
from conftest import run_cli

from idas_sumo.evaluation.geometry import HELD_OUT_GEOMETRIES, SAMPLE_GEOMETRIES
from idas_sumo.sim.netgen import NetParams


def test_held_out_geometries_differ_from_the_shipped_net() -> None:
    names = [name for name, _ in HELD_OUT_GEOMETRIES]
    assert len(set(names)) == len(names)
    assert all(params != NetParams() for _, params in HELD_OUT_GEOMETRIES)
    assert "onramp" in SAMPLE_GEOMETRIES


@pytest.mark.sumo
def test_geometry_suite_writes_one_table_per_geometry(tmp_path: Path) -> None:
    out = tmp_path / "geo"
    env = {**os.environ, "IDAS_SUMO_CACHE": str(tmp_path / "cache"), "PYTHONUNBUFFERED": "1"}
    args = ["evaluate", "--suite", "geometry", "--baseline", "idm", "--scenarios", "1", "--no-progress"]
    result = run_cli(*args, "--out", str(out), env=env, timeout=180.0)
    assert result.returncode == 0, result.stderr
    expected = [name for name, _ in HELD_OUT_GEOMETRIES] + list(SAMPLE_GEOMETRIES)
    for name in expected:
        assert f"geometry {name}:" in result.stdout
        assert (out / name / "episodes.csv").is_file()
    with (out / "geometry.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [r["geometry"] for r in rows] == expected
    assert all(r["method"] == "idm" and r["scenarios"] == "1" for r in rows)


@pytest.mark.parametrize(
    ("extra", "flag"),
    [(("--net", "x.net.xml"), "--net"), (("--junction", "j1"), "--junction")],
)
def test_geometry_suite_refuses_a_net_or_junction(tmp_path: Path, extra: tuple[str, str], flag: str) -> None:
    result = run_cli(
        "evaluate", "--suite", "geometry", "--baseline", "idm", *extra, "--out", str(tmp_path / "o")
    )
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and f"leave out {flag}" in lines[0]
    assert not (tmp_path / "o").exists()
