"""Field checks shared by the frozen config dataclasses: each raises a one-line ValueError that
names the class, the field and the value it got."""

from __future__ import annotations

from typing import Any


def _fail(obj: Any, name: str, what: str) -> None:
    raise ValueError(f"{type(obj).__name__}.{name} must be {what}, got {getattr(obj, name)!r}")


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def integers(obj: Any, *names: str, minimum: int = 1, optional: bool = False) -> None:
    """Each field is an integer >= `minimum` (None also allowed when `optional`)."""
    for name in names:
        value = getattr(obj, name)
        if optional and value is None:
            continue
        if not _is_int(value) or value < minimum:
            what = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"
            _fail(obj, name, ("None or " if optional else "") + what)


def positive(obj: Any, *names: str) -> None:
    """Each field is a number > 0 (NaN fails)."""
    for name in names:
        if not getattr(obj, name) > 0:
            _fail(obj, name, "positive")


def non_negative(obj: Any, *names: str) -> None:
    """Each field is a number >= 0 (NaN fails)."""
    for name in names:
        if not getattr(obj, name) >= 0:
            _fail(obj, name, ">= 0")


def unit_interval(obj: Any, *names: str, open_right: bool = False) -> None:
    """Each field lies in [0, 1] ([0, 1) when `open_right`)."""
    for name in names:
        value = getattr(obj, name)
        if not (0.0 <= value < 1.0 if open_right else 0.0 <= value <= 1.0):
            _fail(obj, name, "in [0, 1)" if open_right else "in [0, 1]")


def booleans(obj: Any, *names: str, optional: bool = False) -> None:
    """Each field is True or False (None also allowed when `optional`)."""
    for name in names:
        value = getattr(obj, name)
        if not (isinstance(value, bool) or (optional and value is None)):
            _fail(obj, name, ("None, " if optional else "") + "True or False")
