"""What the configuration dataclasses share: their fields' resolved types, and a check that each
`Literal`-typed field holds one of its choices (run by their `__post_init__`, so a config built
by hand, read back from a run.json or made by `dataclasses.replace` is checked alike)."""

from __future__ import annotations

from dataclasses import fields
from functools import cache
from typing import Literal, get_args, get_origin, get_type_hints


@cache
def field_types(cls: type) -> dict[str, object]:
    """{field name: its annotation, resolved} of a dataclass."""
    return get_type_hints(cls)


def choices(annotation) -> tuple | None:
    """The values a `Literal[...]` annotation allows; None for any other annotation."""
    return get_args(annotation) if get_origin(annotation) is Literal else None


def check_choices(obj, prefix: str = "") -> None:
    """Raise ValueError naming the field (as `prefix` + name) whose value is not one of its
    Literal choices."""
    for name, annotation in field_types(type(obj)).items():
        allowed = choices(annotation)
        if allowed is not None and getattr(obj, name) not in allowed:
            raise ValueError(f"{prefix}{name} must be one of {', '.join(allowed)}, got {getattr(obj, name)!r}")


def json_object(d, name: str) -> dict:
    """A copy of `d`, read from a file, or ValueError naming it when it is not a JSON object."""
    if not isinstance(d, dict):
        raise ValueError(f"{name} must be a JSON object, got {type(d).__name__}")
    return dict(d)


def from_fields(cls: type, d, prefix: str = ""):
    """`cls(**d)` for a dict read from a file, with a ValueError naming the field (as `prefix` +
    name) when `d` is not a dict, has a key `cls` does not know, or misses one it needs."""
    name = prefix.rstrip(".") or cls.__name__
    d = json_object(d, name)
    unknown = sorted(set(d) - {f.name for f in fields(cls)})
    if unknown:
        raise ValueError(f"{prefix}{unknown[0]} is not a setting of {cls.__name__}")
    try:
        return cls(**d)
    except TypeError as exc:  # a required field missing
        raise ValueError(f"{name}: {exc}") from None
