"""``config.from_dict``: retired keys load at their former default and are refused with any other value."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import pytest

from idas_sumo.config import from_dict
from idas_sumo.errors import InputError


@dataclass(frozen=True)
class _Config:
    kept: int = 1
    RETIRED_KEYS: ClassVar[dict[str, Any]] = {"old_switch": "paper"}


def test_a_retired_key_at_its_former_default_is_dropped() -> None:
    assert from_dict(_Config, {"kept": 3, "old_switch": "paper"}, "f.toml") == _Config(kept=3)


def test_a_retired_key_with_a_variant_value_is_one_clear_error() -> None:
    with pytest.raises(InputError, match=r"f\.toml\.old_switch: 'variant' is a retired experiment variant"):
        from_dict(_Config, {"old_switch": "variant"}, "f.toml")


def test_an_unknown_key_is_still_refused() -> None:
    with pytest.raises(InputError, match="unknown key 'old_swich'"):
        from_dict(_Config, {"old_swich": "paper"}, "f.toml")
