"""One EnvConfig and one merge site per run: the net is parsed once at the edge, the site travels.

The counts patch the one net parser behind every merge site (``load_sumo_net`` as ``detect_merges``
calls it) and run a whole command in this process."""

from __future__ import annotations

import json
import pickle
import shutil
from pathlib import Path

import pytest
import torch

from idas_sumo.cli import main
from idas_sumo.config import load_toml
from idas_sumo.env.config import EnvConfig
from idas_sumo.errors import InputError
from idas_sumo.evaluation.protocol import EvalConfig, load_eval_config
from idas_sumo.evaluation.replay import REPLAY_DIR, RUN_NAME, load_replay_data, replay_episode
from idas_sumo.resources import POLICY_DIR, SCENARIO_DIR
from idas_sumo.sim import merge_detect
from idas_sumo.sim.merge_detect import choose_merge
from idas_sumo.training.checkpoint import load_checkpoint
from idas_sumo.training.config import load_train_config, train_config_from_dict


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


# -- the episode rules' one home, read from the files written before it -----------------------------

REPLAY_BASE = Path(__file__).parent / "data" / "replay_base"
"""``evaluate --baseline idm --others idm --scenarios 2 --seed 5 --safety-mask merge_aware`` as the code
before ``EnvConfig`` travelled wrote it (commit 66d8443): its replay record must still replay."""


def test_a_flat_recipe_lands_in_env_and_goes_back_flat(tmp_path: Path) -> None:
    path = tmp_path / "t.toml"
    path.write_text('max_episode_s = 12.5\nsafety_mask = "merge_aware"\njunction = ""\nseed = 3\n[reward]\n')
    config = load_train_config(path)
    assert config.env == EnvConfig(max_episode_s=12.5, safety_mask="merge_aware") and config.seed == 3
    plain = config.as_dict()
    assert "env" not in plain and plain["max_episode_s"] == 12.5 and plain["safety_mask"] == "merge_aware"
    assert train_config_from_dict(plain, "checkpoint") == config
    assert config.with_overrides(junction="j2").env.junction == "j2"


def test_a_nested_env_table_and_a_flat_typo_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "t.toml"
    path.write_text("[env]\nmax_episode_s = 12.0\n")
    with pytest.raises(InputError, match="unknown key 'env' \\(write its keys flat: max_episode_s"):
        load_train_config(path)
    path.write_text("max_episode = 12.0\n")
    with pytest.raises(InputError, match='did you mean "max_episode_s"'):
        load_train_config(path)
    path.write_text("max_episode_s = -1.0\n")
    with pytest.raises(InputError, match=f"^{path}: max_episode_s must be positive"):
        load_train_config(path)


@pytest.mark.parametrize(
    "recipe",
    [
        *sorted((SCENARIO_DIR).glob("train*.toml")),
        *sorted((Path(__file__).parents[1] / "experiments" / "recipes").glob("*.toml")),
    ],
    ids=lambda p: p.name,
)
def test_every_recipe_reads_its_flat_episode_rules(recipe: Path) -> None:
    """Shipped and experiment recipes: loaded (or refused as a retired variant, as before), their flat
    keys in ``env``."""
    data = load_toml(recipe)
    try:
        config = load_train_config(recipe)
    except InputError as err:
        assert "retired" in str(err)
        return
    assert config.env.max_episode_s == data.get("max_episode_s", EnvConfig().max_episode_s)
    assert config.env.safety_mask == data.get("safety_mask", EnvConfig().safety_mask)
    assert config.env.junction == (data.get("junction") or None)


@pytest.mark.parametrize("policy", sorted(POLICY_DIR.glob("*.pt")), ids=lambda p: p.name)
def test_shipped_checkpoints_still_load_their_flat_config(policy: Path) -> None:
    stored = torch.load(policy, weights_only=True, map_location="cpu")["config"]
    config = load_checkpoint(policy).config
    assert config.env.max_episode_s == stored["max_episode_s"]
    assert config.env.safety_mask == stored["safety_mask"] and config.env.junction is None


def test_an_eval_config_holds_only_its_rules(tmp_path: Path) -> None:
    path = tmp_path / "e.toml"
    path.write_text('max_episode_s = 30.0\nsafety_mask = "merge_aware"\n[traffic]\nn_vehicles = 4\n')
    config = load_eval_config(path)
    assert config.env == EnvConfig(max_episode_s=30.0, safety_mask="merge_aware")
    assert config.traffic.n_vehicles == 4
    for text, what in (
        ('[reward]\nextra_terms = ["flow_bonus"]\n', "reward"),
        ('junction = "j2"\n', "--junction"),
    ):
        path.write_text(text)
        with pytest.raises(InputError, match=what):
            load_eval_config(path)
    path.write_text("[reward]\n")  # the paper's reward, spelt out: allowed
    assert load_eval_config(path) == EvalConfig()


@pytest.mark.sumo
def test_a_replay_record_written_before_still_replays(tmp_path: Path) -> None:
    out = tmp_path / "old"
    shutil.copytree(REPLAY_BASE, out)
    data = load_replay_data(out)
    assert data.env == EnvConfig(max_episode_s=60.0, safety_mask="merge_aware", junction="merge_point")
    replay = replay_episode(out, "paper-001")
    assert replay.identical and replay.original_row == 2
    # Older still: no junction kept (single-merge nets only).
    run_json = out / REPLAY_DIR / RUN_NAME
    run = json.loads(run_json.read_text())
    del run["junction"]
    run_json.write_text(json.dumps(run))
    assert load_replay_data(out).env.junction is None
    assert replay_episode(out, "paper-000").identical


def test_a_new_replay_record_keeps_the_keys_of_the_old(tmp_path: Path, net_path: Path) -> None:
    out = tmp_path / "new"
    argv = ["evaluate", "--net", str(net_path), "--baseline", "idm", "--others", "idm", "--scenarios", "2"]
    argv += [
        "--config",
        str(SCENARIO_DIR / "eval_paper_as_drawn.toml"),
    ]  # the generator the record was drawn with
    assert (
        main([*argv, "--seed", "5", "--safety-mask", "merge_aware", "--out", str(out), "--no-progress"]) == 0
    )
    for name in (f"{REPLAY_DIR}/{RUN_NAME}", "settings.json"):
        new, old = json.loads((out / name).read_text()), json.loads((REPLAY_BASE / name).read_text())
        assert list(new) == list(old)
        assert {k: v for k, v in new.items() if "sha256" not in k} == {
            k: v for k, v in old.items() if "sha256" not in k
        } or name == "settings.json"
    assert (out / "episodes.csv").read_text() == (REPLAY_BASE / "episodes.csv").read_text()
