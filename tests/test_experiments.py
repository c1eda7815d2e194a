"""The experiments beside the core: every recipe either still runs on the core's options or is refused as a
retired variant, and experiments/README.md says which; a smoke run of each recipe that still runs."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from idas_sumo.config import RETIRED_NOTE
from idas_sumo.errors import InputError
from idas_sumo.resources import POLICY_DIR
from idas_sumo.training.config import TrainConfig, load_train_config

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
RECIPES = sorted((EXPERIMENTS / "recipes").glob("*.toml"))


def _loads(recipe: Path) -> TrainConfig | None:
    """The recipe's config, or None when the core refuses it as a retired variant (any other error fails)."""
    try:
        return load_train_config(recipe)
    except InputError as err:
        assert RETIRED_NOTE in str(err), err
        return None


def _verdicts(recipe: Path) -> list[str]:
    """The verdict cells of the experiments/README.md table rows that name ``recipe``."""
    rows = (EXPERIMENTS / "README.md").read_text(encoding="utf-8").splitlines()
    cells = [row.split(" | ") for row in rows if row.startswith("|") and f"`{recipe.name}`" in row]
    return [c[3] for c in cells if len(c) >= 5]


def test_there_are_experiment_recipes_of_both_kinds() -> None:
    loaded = [_loads(r) for r in RECIPES]
    assert sum(c is None for c in loaded) >= 10 and sum(c is not None for c in loaded) >= 5


@pytest.mark.parametrize("recipe", RECIPES, ids=lambda p: p.stem)
def test_a_refused_recipe_is_a_retired_row_of_the_table(recipe: Path) -> None:
    verdicts = _verdicts(recipe)
    assert verdicts, f"experiments/README.md has no table row naming {recipe.name}"
    if _loads(recipe) is None:
        assert any("retired" in v for v in verdicts), (recipe.name, verdicts)


def _smoke_config(config: TrainConfig) -> TrainConfig:
    """The recipe with two short episodes per stage, one process, from the shipped IDAS-V when it starts from
    a checkpoint (its own ``init_from`` names a run of ours under runs/)."""
    return dataclasses.replace(
        config,
        robot_episodes=2,
        intelligent_episodes=2,
        direct_episodes=2,
        episodes_per_update=2,
        checkpoint_every=2,
        workers=1,
        copies=2,
        # a generated merge may need longer than the T-junction for its slowest car to finish
        env=dataclasses.replace(
            config.env, max_episode_s=config.env.max_episode_s if config.geometry else 12.0
        ),
        validate_every=2 if config.validate_every else 0,
        # each validation merge of a [geometry] recipe needs a scenario of its own
        validation_scenarios=max(2, config.geometry.validation_geometries if config.geometry else 0),
        init_from=str(POLICY_DIR / "idas_v.pt") if config.init_from else "",
    )


@pytest.mark.sumo
@pytest.mark.parametrize("recipe", [r for r in RECIPES if _loads(r) is not None], ids=lambda p: p.stem)
def test_a_kept_recipe_still_trains(recipe: Path, net_path: Path, tmp_path: Path) -> None:
    from idas_sumo.training.loop import run_training

    config = _loads(recipe)
    assert config is not None
    final = run_training(net_path, _smoke_config(config), tmp_path / "run", progress=False)
    assert final.is_file() and (tmp_path / "run" / "metrics.csv").stat().st_size > 0
