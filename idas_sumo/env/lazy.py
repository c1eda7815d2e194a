"""``lazy``: ``functools.cached_property`` without its lock.

Python 3.11's ``cached_property`` takes a lock on every first read (removed in 3.12); the engine reads a few
of them per step on fresh objects (the snapshot's distance order, a batch's observations), where the lock
cost more than the value. The objects are never shared between threads while they are filled.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Generic, TypeVar, overload

T = TypeVar("T")


class lazy(Generic[T]):  # (lower case: a decorator, like cached_property)
    """A value computed on first read and kept in the instance's ``__dict__`` (frozen dataclasses too)."""

    def __init__(self, func: Callable[[Any], T]) -> None:
        self.func = func
        self.name = func.__name__
        self.__doc__ = func.__doc__

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    @overload
    def __get__(self, obj: None, owner: type | None = None) -> lazy[T]: ...

    @overload
    def __get__(self, obj: object, owner: type | None = None) -> T: ...

    def __get__(self, obj: object | None, owner: type | None = None) -> T | lazy[T]:
        if obj is None:
            return self
        value = self.func(obj)
        obj.__dict__[self.name] = value
        return value
