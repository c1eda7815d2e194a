"""Shared fixtures: the default net, a freshly generated net, and one place that shrinks test budgets."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_NET = REPO_ROOT / "sumo_nets" / "tjunction.net.xml"


@dataclass(frozen=True)
class SmallBudget:
    """Sizes that keep SUMO-backed tests fast (change them here, not in the tests)."""

    episodes: int = 3
    max_vehicles_per_road: int = 3
    max_episode_s: float = 20.0
    api_cycles: int = 30
    """num_cycles for the PettingZoo API test."""


@pytest.fixture(scope="session")
def small_budget() -> SmallBudget:
    return SmallBudget()


@pytest.fixture(scope="session")
def net_path() -> Path:
    """The committed default network."""
    return DEFAULT_NET


@pytest.fixture(scope="session")
def fresh_net(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The default network regenerated with netconvert into a temporary directory (once per session)."""
    from idas_sumo.sim.netgen import generate_net

    return generate_net(tmp_path_factory.mktemp("net") / "tjunction.net.xml")


@pytest.fixture(scope="session")
def merge_net(net_path: Path):  # type: ignore[no-untyped-def]
    """The committed default network, read and validated."""
    from idas_sumo.sim.netgen import read_merge_net

    return read_merge_net(net_path)
