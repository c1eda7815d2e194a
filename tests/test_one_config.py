"""One EnvConfig and one merge site per run: the net is parsed once at the edge, the site travels.

The counts patch the one net parser behind every merge site (``load_sumo_net`` as ``detect_merges``
calls it) and run a whole command in this process."""

from __future__ import annotations

import pickle
from pathlib import Path

import pytest

from idas_sumo.cli import main
from idas_sumo.sim import merge_detect
from idas_sumo.sim.merge_detect import choose_merge


@pytest.fixture
def parse_count(monkeypatch: pytest.MonkeyPatch) -> list[Path]:
    """Every net file parsed into merge sites while the test runs."""
    parsed: list[Path] = []
    real = merge_detect.load_sumo_net

    def counting(path: str | Path) -> object:
        parsed.append(Path(path))
        return real(path)

    monkeypatch.setattr(merge_detect, "load_sumo_net", counting)
    return parsed


def test_a_train_run_parses_its_net_once(tmp_path: Path, net_path: Path, parse_count: list[Path]) -> None:
    config = tmp_path / "tiny.toml"
    config.write_text(
        'stage = "direct"\ndirect_episodes = 2\nepisodes_per_update = 2\ncheckpoint_every = 2\n'
        "max_episode_s = 6.0\ncopies = 2\nvalidate_every = 2\nvalidation_scenarios = 2\n"
    )
    argv = ["train", "--net", str(net_path), "--config", str(config), "--workers", "1"]
    assert main([*argv, "--out", str(tmp_path / "run"), "--no-progress"]) == 0
    assert parse_count == [net_path]


def test_an_evaluation_parses_its_net_once(tmp_path: Path, net_path: Path, parse_count: list[Path]) -> None:
    argv = ["evaluate", "--net", str(net_path), "--baseline", "idm", "--others", "idm", "--scenarios", "2"]
    assert main([*argv, "--out", str(tmp_path / "eval"), "--no-progress"]) == 0
    assert parse_count == [net_path]


def test_the_merge_site_pickles(net_path: Path) -> None:
    """It travels to worker processes and Ray actors."""
    site = choose_merge(net_path)
    assert pickle.loads(pickle.dumps(site)) == site
