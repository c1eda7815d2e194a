"""Each shipped policy's JSON agrees with the checkpoint it describes: its file's SHA-256, the stage, the episode
picked, whether the central critic was on, the seed, and the recipes it names ship in the package."""

from __future__ import annotations

import json
import re
import zlib
from pathlib import Path
from typing import Any

import pytest
import torch

from idas_sumo.evaluation.policies import LEARNED_METHODS
from idas_sumo.io_utils import file_digest
from idas_sumo.resources import POLICY_DIR, SCENARIO_DIR

SHIPPED = sorted(LEARNED_METHODS)


def _metadata(name: str) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((POLICY_DIR / f"{name}.json").read_text(encoding="utf-8"))
    return data


def _checkpoint(name: str) -> dict[str, Any]:
    data: dict[str, Any] = torch.load(POLICY_DIR / f"{name}.pt", map_location="cpu", weights_only=True)
    return data


def test_the_package_ships_exactly_the_learned_methods_policies() -> None:
    assert sorted(p.stem for p in POLICY_DIR.glob("*.pt")) == SHIPPED
    assert sorted(p.stem for p in POLICY_DIR.glob("*.json")) == SHIPPED
    assert SHIPPED == ["idas", "idas_direct", "idas_geometry", "idas_v"]


@pytest.mark.parametrize("name", SHIPPED)
def test_metadata_agrees_with_its_checkpoint(name: str) -> None:
    meta, ckpt = _metadata(name), _checkpoint(name)
    assert meta["policy"] == name and meta["file"] == LEARNED_METHODS[name]
    assert meta["file_sha256"] == file_digest(POLICY_DIR / meta["file"])
    assert meta["stage_of_checkpoint"] == ckpt["stage"]
    assert meta["checkpoint_global_episode"] == ckpt["global_episode"]
    assert meta["picked_by_validation"]["global_episode"] == ckpt["global_episode"]
    assert meta["picked_by_validation"]["stage_episode"] == ckpt["episode"]
    assert meta["run_episodes"] >= ckpt["global_episode"]
    assert meta["seed"] == ckpt["config"]["seed"] == meta["config"]["seed"]
    # The stage decides the central critic (off in the robot world); the learner's state says what ran.
    ran_with = ckpt["learner"]["config"]["use_central_critic"]
    assert meta["central_critic"] is ran_with is (ckpt["stage"] != "robot")
    assert meta["config"]["learner"]["use_central_critic"] is ran_with
    for field in ("lr_actor", "gamma", "alpha", "entropy_coef", "gae_lambda", "q_lambda"):
        assert meta["config"]["learner"][field] == ckpt["learner"]["config"][field], field


@pytest.mark.parametrize("name", SHIPPED)
def test_the_recipes_a_policy_names_ship_in_the_package(name: str) -> None:
    meta = _metadata(name)
    named = [Path(p).name for p in re.findall(r"--config\s+(\S+)", meta["made_with"])]
    assert meta["recipes"] == named and named
    for recipe in named:
        assert (SCENARIO_DIR / recipe).is_file(), recipe


def test_idas_weights_saw_idas_v_episodes_and_its_own() -> None:
    idas, idas_v = _metadata("idas"), _metadata("idas_v")
    # IDAS's stage 2 started from IDAS-V's checkpoint.
    assert idas["config"]["init_from"] == idas_v["source_checkpoint"]
    assert idas_v["rl_episodes_in_weights"] == idas_v["checkpoint_global_episode"] == 2000
    assert (
        idas["rl_episodes_in_weights"]
        == 2000 + 2512
        == (idas_v["checkpoint_global_episode"] + idas["checkpoint_global_episode"])
    )


def test_the_shipped_policies_keep_the_wheel_under_15_mb() -> None:
    # The wheel is these files, deflated as a wheel's zip does, plus about 0.4 MB of code and data.
    deflated = sum(len(zlib.compress(p.read_bytes(), 6)) for p in POLICY_DIR.iterdir() if p.is_file())
    assert deflated <= 14_500_000
