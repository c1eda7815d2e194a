"""A wheel of the checkout, installed into a fresh venv and used from a directory outside the repository:
the shipped net, policies and scenario TOML must travel as package data (nothing may assume the checkout).

The fresh venv sees this environment's dependencies (torch, SUMO, ...) through a ``.pth`` file naming
our site-packages, so nothing is downloaded. ``.pth`` files inside a directory added that way are not
processed, so the editable install's finder stays off and ``idas_sumo`` comes only from the wheel.
"""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
import sysconfig
from dataclasses import dataclass
from pathlib import Path

import pytest

pytestmark = pytest.mark.sumo

REPO_ROOT = Path(__file__).resolve().parents[1]
BUILD_INPUTS = ("pyproject.toml", "README.md", "idas_sumo")
"""What the build reads (pyproject names README.md as the long description)."""


@dataclass(frozen=True)
class Installed:
    venv: Path
    python: Path
    script: Path
    package_dir: Path
    """Where the installed ``idas_sumo`` lives, as the fresh venv's Python reports it."""
    source: Path
    """The copy of the checkout the wheel was built from."""
    outside: Path
    """A directory outside the repository to run commands from."""
    env: dict[str, str]


def _run(cmd: list[str | Path], cwd: Path, env: dict[str, str] | None = None, timeout: float = 120.0) -> str:
    result = subprocess.run(
        [str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )
    assert result.returncode == 0, f"{cmd} exited {result.returncode}:\n{result.stdout}\n{result.stderr}"
    return result.stdout


def _package_files(root: Path) -> set[str]:
    return {
        p.relative_to(root).as_posix()
        for p in root.rglob("*")
        if p.is_file() and "__pycache__" not in p.parts and not p.name.endswith(".pyc")
    }


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Installed:
    tmp = tmp_path_factory.mktemp("install")
    # Build from a copy: building in the checkout leaves build/lib behind, whose stale files would end
    # up in the next wheel and hide missing package data.
    source = tmp / "source"
    source.mkdir()
    for name in BUILD_INPUTS:
        src = REPO_ROOT / name
        if src.is_dir():
            shutil.copytree(src, source / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(src, source / name)
    dist = tmp / "dist"
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "--no-input"]
    _run([*pip, "wheel", "-q", "--no-deps", "--no-build-isolation", source, "-w", dist], cwd=tmp)
    (wheel,) = dist.glob("idas_sumo-*.whl")

    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv], cwd=tmp)
    python = venv / "bin" / "python"
    purelib = _run([python, "-c", "import sysconfig; print(sysconfig.get_path('purelib'))"], tmp)
    ours = sorted({sysconfig.get_path("purelib"), sysconfig.get_path("platlib")})
    (Path(purelib.strip()) / "_idas_test_deps.pth").write_text("\n".join(ours) + "\n")
    _run([*pip, "--python", python, "install", "-q", "--no-deps", "--no-index", wheel], cwd=tmp)

    outside = tmp / "elsewhere"
    outside.mkdir()
    our_bin = str(Path(sys.prefix) / "bin")
    path = [str(venv / "bin"), *(p for p in os.environ.get("PATH", "").split(os.pathsep) if p != our_bin)]
    env = {
        **{k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")},
        "VIRTUAL_ENV": str(venv),
        "PATH": os.pathsep.join(path),
        "PYTHONUNBUFFERED": "1",
    }
    package_dir = Path(
        _run(
            [python, "-c", "import idas_sumo, pathlib; print(pathlib.Path(idas_sumo.__file__).parent)"],
            outside,
            env,
        ).strip()
    )
    return Installed(venv, python, venv / "bin" / "idas-sumo", package_dir, source, outside, env)


def test_the_package_comes_from_the_wheel_with_every_data_file(installed: Installed) -> None:
    assert installed.package_dir.is_relative_to(installed.venv), installed.package_dir
    expected = _package_files(installed.source / "idas_sumo")
    assert {"sumo_nets/tjunction.net.xml", "policies/idas.pt", "scenarios/representative/s1.toml"} <= expected
    missing = expected - _package_files(installed.package_dir)
    assert not missing, f"not in the wheel: {sorted(missing)}"


def test_evaluate_the_shipped_idas_from_another_directory(installed: Installed) -> None:
    _run(
        [
            installed.script,
            "evaluate",
            "--baseline",
            "idas",
            "--scenarios",
            "2",
            "--out",
            "X",
            "--no-progress",
        ],
        installed.outside,
        installed.env,
    )
    with (installed.outside / "X" / "episodes.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["method"] for r in rows] == ["idas", "idas"]


def test_train_on_the_shipped_net_from_another_directory(installed: Installed) -> None:
    # The names exactly as the README gives them: no sumo_nets/ or scenarios/ exists here.
    assert not (installed.outside / "sumo_nets").exists()
    args = ["--net", "sumo_nets/tjunction.net.xml", "--config", "scenarios/train_smoke.toml"]
    _run(
        [installed.script, "train", *args, "--stage", "robot", "--out", "R", "--no-progress"],
        installed.outside,
        installed.env,
    )
    assert (installed.outside / "R" / "robot.pt").is_file()


def test_gymnasium_make_from_another_directory(installed: Installed) -> None:
    code = (
        "import gymnasium, idas_sumo\n"
        "env = gymnasium.make('idas_sumo/Merge-v0')\n"
        "env.reset(seed=0)\n"
        "env.close()\n"
        "print(idas_sumo.__file__)\n"
    )
    out = _run([installed.python, "-c", code], installed.outside, installed.env)
    assert Path(out.strip()).is_relative_to(installed.venv)
