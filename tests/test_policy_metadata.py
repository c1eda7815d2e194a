"""Each shipped policy's JSON agrees with the checkpoint it describes: its file's SHA-256, the stage, the episode
picked and its validation score, whether the central critic was on, the seed, the whole training config (γ, λ,
learning rates, episodes, traffic, ...), the RL episodes its weights saw, and the recipes it names ship in the
package."""

from __future__ import annotations

import dataclasses
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
from idas_sumo.training.checkpoint import config_as_it_ran
from idas_sumo.training.config import TrainConfig, train_config_from_dict

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
    assert SHIPPED == [
        "idas",
        "idas_direct",
        "idas_direct_paper",
        "idas_geometry",
        "idas_paper",
        "idas_v",
        "idas_v_paper",
        "warm_start",
    ]


def _stated_config(meta: dict[str, Any], ckpt: dict[str, Any]) -> tuple[TrainConfig, TrainConfig]:
    """The config the JSON states and the one the checkpoint stores, the latter read as ``--resume`` reads it (a
    key the checkpoint lacks is the value the run used before the key existed, else its default; a retired key
    is accepted only at its old default). The central critic is
    the stage's (training/curriculum.py), so the JSON records what the learner ran with."""
    stored = train_config_from_dict(config_as_it_ran(ckpt["config"]), "checkpoint")
    ran_with = ckpt["learner"]["config"]["use_central_critic"]
    stored = dataclasses.replace(
        stored, learner=dataclasses.replace(stored.learner, use_central_critic=ran_with)
    )
    return train_config_from_dict(meta["config"], "json"), stored


@pytest.mark.parametrize("name", SHIPPED)
def test_metadata_agrees_with_its_checkpoint(name: str) -> None:
    meta, ckpt = _metadata(name), _checkpoint(name)
    assert meta["policy"] == name and meta["file"] == LEARNED_METHODS[name]
    assert meta["file_sha256"] == file_digest(POLICY_DIR / meta["file"])
    assert meta["stage_of_checkpoint"] == ckpt["stage"]
    assert meta["checkpoint_global_episode"] == ckpt["global_episode"]
    assert meta["run_episodes"] >= ckpt["global_episode"]
    assert meta["rl_episodes_in_weights"] >= ckpt["global_episode"]
    assert meta["config"]["seed"] == ckpt["config"]["seed"]
    if ckpt["stage"].startswith("imitation-"):
        # The imitation's seed is its own flag (scripts/pretrain_imitation.py --seed), kept as its torch state.
        assert ckpt["torch_rng"].equal(torch.Generator().manual_seed(meta["seed"]).get_state())
    else:
        assert meta["seed"] == ckpt["config"]["seed"]
    pick = meta["picked_by_validation"]
    assert (pick is None) is (ckpt.get("validation") is None)
    if pick is not None:
        assert pick["global_episode"] == ckpt["global_episode"]
        assert pick["stage_episode"] == ckpt["episode"]
        assert pick["validation_seed"] == ckpt["config"]["validation_seed"]
        assert pick["success_rate"] == round(ckpt["validation"]["success_rate"], 4)
        assert pick["joint_return"] == round(ckpt["validation"]["joint_return"], 4)
    # Only the intelligent world's stages train Q (the robot stage and the imitation do not).
    ran_with = ckpt["learner"]["config"]["use_central_critic"]
    assert meta["central_critic"] is ran_with is (ckpt["stage"] in ("intelligent", "direct"))
    stated, stored = _stated_config(meta, ckpt)
    assert stated == stored
    # The learner's own state: what the weights were trained with (the imitation overrides the learning rates).
    for field in ("gamma", "alpha", "entropy_coef", "gae_lambda", "q_lambda", "normalize_advantages"):
        assert getattr(stated.learner, field) == ckpt["learner"]["config"][field], field


def test_a_checkpoint_older_than_a_default_reads_as_it_ran() -> None:
    """idas_geometry.pt predates ``q_horizon`` and ``entries``: it trained Q along its agent's steps, drew entries
    as drawn."""
    ckpt = _checkpoint("idas_geometry")
    assert (
        "q_horizon" not in ckpt["config"]["learner"]
        and "entries" not in ckpt["config"]["intelligent_traffic"]
    )
    stored = train_config_from_dict(config_as_it_ran(ckpt["config"]), "checkpoint")
    assert stored.learner.q_horizon == "agent" and TrainConfig().learner.q_horizon == "episode"
    assert stored.robot_traffic.entries == stored.intelligent_traffic.entries == "as_drawn"
    assert TrainConfig().intelligent_traffic.entries == "feasible"
    written = {**ckpt["config"], "learner": {**ckpt["config"]["learner"], "q_horizon": "episode"}}
    assert config_as_it_ran(written)["learner"]["q_horizon"] == "episode"  # a written value stands


def test_the_metadata_check_fails_on_a_wrong_claim() -> None:
    meta, ckpt = _metadata("idas"), _checkpoint("idas")
    wrong = {**meta, "config": {**meta["config"], "learner": {**meta["config"]["learner"], "gamma": 0.9}}}
    stated, stored = _stated_config(wrong, ckpt)
    assert stated != stored


def test_the_warm_start_is_what_our_recipe_started_from() -> None:
    warm = _metadata("warm_start")
    assert warm["rl_episodes_in_weights"] == warm["checkpoint_global_episode"] == 0
    assert warm["stage_of_checkpoint"] == f"imitation-{warm['teacher']}" == "imitation-fsm_idm_smooth"
    for name in ("idas", "idas_v", "idas_direct"):
        meta = _metadata(name)
        assert meta["init_from_sha256"] == warm["file_sha256"], name
        assert meta["rl_episodes_in_weights"] == meta["checkpoint_global_episode"], name
    for name in ("idas_paper", "idas_v_paper", "idas_direct_paper"):  # from random weights
        meta = _metadata(name)
        assert meta["config"]["init_from"] == "" and meta["init_from_sha256"] is None, name


@pytest.mark.parametrize("name", SHIPPED)
def test_the_recipes_a_policy_names_ship_in_the_package(name: str) -> None:
    meta = _metadata(name)
    named = [Path(p).name for p in re.findall(r"--config\s+(\S+)", meta["made_with"])]
    assert meta["recipes"] == named and named
    for recipe in named:
        assert (SCENARIO_DIR / recipe).is_file(), recipe


@pytest.mark.parametrize("recipe", ["", "_paper"])
def test_idas_weights_saw_its_robot_stage_and_its_own(recipe: str) -> None:
    """IDAS is a curriculum run's intelligent stage: its weights saw the run's whole robot stage first."""
    idas = _metadata(f"idas{recipe}")
    robot = idas["config"]["robot_episodes"]
    assert idas["stages"]["robot"]["episodes"] == robot
    assert idas["rl_episodes_in_weights"] == robot + idas["picked_by_validation"]["stage_episode"]
    assert idas["stage_of_checkpoint"] == "intelligent"
    assert _metadata(f"idas_v{recipe}")["stage_of_checkpoint"] == "robot"
    assert _metadata(f"idas_direct{recipe}")["stage_of_checkpoint"] == "direct"


def test_the_shipped_policies_keep_the_wheel_under_25_mb() -> None:
    # The wheel is these files, deflated as a wheel's zip does, plus about 0.4 MB of code and data: eight
    # checkpoints of about 2.8 MB each (networks, critics, optimiser state: each can start a run with init_from).
    deflated = sum(len(zlib.compress(p.read_bytes(), 6)) for p in POLICY_DIR.iterdir() if p.is_file())
    assert deflated <= 24_500_000
