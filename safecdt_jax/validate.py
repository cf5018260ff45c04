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


def one_of(obj: Any, name: str, choices: tuple[str, ...]) -> None:
    """The field is one of `choices` (a rule or algorithm named by text)."""
    if getattr(obj, name) not in choices:
        _fail(obj, name, f"one of {', '.join(choices)}")


def field_overrides(items: list[str], *classes: type) -> dict[str, Any]:
    """`["steps=20000", "lora_labels=target"]` -> `{"steps": 20000, "lora_labels": "target"}`,
    the `--set FIELD=VALUE` items of a command line: a value is read as an int, a float, a
    bool (true/false) or None (none) where it parses as one, else kept as text. Raises a
    one-line ValueError for an item without '=' or a field that none of the dataclasses
    `classes` has."""
    import dataclasses

    fields = {f.name: f for cls in classes for f in dataclasses.fields(cls)}
    out: dict[str, Any] = {}
    for item in items:
        key, eq, text = item.partition("=")
        if not eq or key not in fields:
            names = "/".join(cls.__name__ for cls in classes)
            raise ValueError(f"--set {item!r}: expected FIELD=VALUE with a field of {names}")
        value: Any = {"true": True, "false": False, "none": None}.get(text.lower(), text)
        for kind in (int, float):
            if isinstance(value, str):
                try:
                    value = kind(text)
                except ValueError:
                    pass
        if isinstance(value, int) and not isinstance(value, bool) and "float" in str(
                fields[key].type):
            value = float(value)  # `cost_offset=1` means 1.0, as the config's type says
        out[key] = value
    return out
