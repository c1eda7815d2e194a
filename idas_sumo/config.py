"""TOML loading into frozen dataclasses: unknown keys are refused with a did-you-mean, types are
checked, and every problem becomes one ``InputError`` line that names the file and the key."""

from __future__ import annotations

import dataclasses
import difflib
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from idas_sumo.errors import InputError

T = TypeVar("T")
MAX_SCENARIOS = 100_000
"""The most scenarios a user may ask one run for, wherever the count comes from (``--scenarios``, a
recipe's ``validation_scenarios``, the Python API): scenarios are drawn up front, so a count is memory
(10^9 filled it before the first episode); the paper uses 100."""
MAX_VEHICLES = 1_000
"""The most cars one scenario may hold, wherever they come from (a scenario file's vehicles, a
``[traffic]`` table's ``n_vehicles`` or twice its ``max_vehicles_per_road``): each is a SUMO vehicle
and a row at every step (``max_vehicles_per_road = 10**9`` drew a billion cars before the first
step); the paper has 8."""
MAX_EPISODES = 100_000_000
"""The most episodes a training stage (or ``--episodes``, ``checkpoint_every``, ``validate_every``)
may name: 1,400 times the paper's 70,000. ``episodes_per_update``'s episodes are drawn up front, so it
is bounded by ``MAX_SCENARIOS`` instead."""
RETIRED_ATTR = "RETIRED_KEYS"
"""A config dataclass may name keys it no longer has, with the value they had by default, in a class attribute of
this name (``RETIRED_KEYS: ClassVar[dict[str, Any]]``). Files written before (checkpoints, recipes) still load when
they hold that value; any other value was a retired experiment's variant, refused with a pointer to its write-up."""
RETIRED_NOTE = "a retired experiment variant (experiments/README.md); this build runs only"
FLAT_ATTR = "FLAT_FIELDS"
"""A config dataclass may keep a nested dataclass field's keys flat in its own table, in a class attribute of this
name (``FLAT_FIELDS: ClassVar[tuple[str, ...]] = ("env",)``): ``max_episode_s = 40`` is then read as
``env.max_episode_s`` (errors name the flat key) and ``to_plain`` writes it flat again, so files written before the
field was nested keep their format."""


def did_you_mean(word: str, choices: typing.Iterable[str]) -> str:
    """' (did you mean "x"?)' for the closest choice, or '' when nothing is close."""
    close = difflib.get_close_matches(word, list(choices), n=1, cutoff=0.5)
    return f' (did you mean "{close[0]}"?)' if close else ""


def load_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML file; a missing file or a syntax error is an InputError naming the file."""
    p = Path(path)
    if p.exists() and not p.is_file() and not p.is_dir():  # reading a FIFO blocks until written to
        raise InputError(f"{p}: not a regular file (a FIFO, device or socket), expected a TOML file")
    try:
        with p.open("rb") as f:
            return tomllib.load(f)
    except RecursionError:  # tomllib recurses into nested arrays and tables
        raise InputError(f"{p}: TOML nested too deeply to read") from None
    except FileNotFoundError:
        raise InputError(f"{p}: file not found") from None
    except IsADirectoryError:
        raise InputError(f"{p}: is a directory, expected a TOML file") from None
    except PermissionError:
        raise InputError(f"{p}: not readable (permission denied)") from None
    except UnicodeDecodeError:
        raise InputError(f"{p}: not a text file") from None
    except tomllib.TOMLDecodeError as err:
        raise InputError(f"{p}: TOML syntax error: {err}") from None


def _check_value(value: Any, annotation: Any, where: str) -> Any:
    origin = typing.get_origin(annotation)
    if annotation is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(annotation)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _check_value(value, arg, where)
            except InputError as err:
                errors.append(str(err))
        raise InputError(errors[0] if errors else f"{where}: unexpected value {value!r}")
    if origin is typing.Literal:
        choices = typing.get_args(annotation)
        if value not in choices:
            raise InputError(f"{where}: {value!r} is not one of {', '.join(map(repr, choices))}")
        return value
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise InputError(f"{where}: expected a list, got {type(value).__name__}")
        (item_type, *_rest) = typing.get_args(annotation)
        return tuple(_check_value(v, item_type, f"{where}[{i}]") for i, v in enumerate(value))
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise InputError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise InputError(f"{where}: must be a finite number, got {value!r}")
        return float(value)
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"{where}: expected an integer, got {value!r}")
        return value
    if annotation is bool:
        if not isinstance(value, bool):
            raise InputError(f"{where}: expected true or false, got {value!r}")
        return value
    if annotation is str:
        if not isinstance(value, str):
            raise InputError(f"{where}: expected a string, got {value!r}")
        return value
    if dataclasses.is_dataclass(annotation):
        return from_dict(typing.cast(type, annotation), value, where)
    raise TypeError(f"unsupported annotation {annotation!r} at {where}")


def _nest_flat(cls: type, data: dict[str, Any], hints: dict[str, Any], where: str) -> dict[str, Any]:
    """``data`` with the keys of each of ``cls``'s ``FLAT_FIELDS`` gathered into that field's table."""
    flat: tuple[str, ...] = getattr(cls, FLAT_ATTR, ())
    data = dict(data)
    for name in flat:
        keys = [f.name for f in dataclasses.fields(hints[name]) if f.init]
        if name in data:
            raise InputError(f"{where}: unknown key {name!r} (write its keys flat: {', '.join(keys)})")
        data[name] = {k: data.pop(k) for k in keys if k in data}
    return data


def from_dict(cls: type[T], data: Any, where: str) -> T:
    """Build dataclass ``cls`` from a TOML table; ``where`` prefixes every error (file and table)."""
    if not isinstance(data, dict):
        raise InputError(f"{where}: expected a table, got {type(data).__name__}")
    assert dataclasses.is_dataclass(cls)
    hints = typing.get_type_hints(cls)
    flat = getattr(cls, FLAT_ATTR, ())
    data = _nest_flat(cls, data, hints, where) if flat else data
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    retired: dict[str, Any] = getattr(cls, RETIRED_ATTR, {})
    for key in data:
        if key in retired and key not in fields:
            if data[key] != retired[key]:
                raise InputError(f"{where}.{key}: {data[key]!r} is {RETIRED_NOTE} {retired[key]!r}")
        elif key not in fields:
            names = [*fields, *(f.name for n in flat for f in dataclasses.fields(hints[n]))]
            raise InputError(f"{where}: unknown key {key!r}{did_you_mean(key, names)}")
    kwargs: dict[str, Any] = {}
    for name, field in fields.items():
        if name in data:
            kwargs[name] = _check_value(data[name], hints[name], where if name in flat else f"{where}.{name}")
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise InputError(f"{where}: missing required key {name!r}")
    try:
        return cls(**kwargs)
    except ValueError as err:  # __post_init__ range checks
        raise InputError(f"{where}: {err}") from None


def to_plain(config: Any) -> dict[str, Any]:
    """A config dataclass as a plain nested dict (TOML/checkpoint friendly), its ``FLAT_FIELDS`` flat."""
    data = dataclasses.asdict(config)
    for name in getattr(config, FLAT_ATTR, ()):
        data.update(data.pop(name))
    return data
