"""The `kgs-app` command line's arguments: a job's options built from its schema
(`kgs_core.job_options`: `add_options`, `options_from`), and argparse types for the rest."""

from __future__ import annotations

import argparse
import json
import typing

from pydantic import BaseModel, ValidationError


def setting(text: str) -> tuple[str, object]:
    """argparse type: KEY=VALUE of a training setting (`parse_setting`)."""
    from kgs_core.train.settings import parse_setting

    try:
        return parse_setting(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (an iteration count)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _optional(annotation):
    """`X` of `X | None`, else the annotation."""
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    return args[0] if len(args) == 1 and type(None) in typing.get_args(annotation) else annotation


def add_options(
    p: argparse.ArgumentParser,
    model: type[BaseModel],
    positional: tuple[str, ...] = (),
    flags: dict[str, str] | None = None,
    extra_help: dict[str, str] | None = None,
    metavars: dict[str, str] | None = None,
) -> None:
    """An argument per field of `model`: `--field-name` (or a positional, or the flag `flags`
    names), with its description as help. Values go to the model unconverted, so that the model,
    not argparse, refuses a bad one, in the words the server uses (`options_from`). An option
    not given is left out and the model's default applies; a switch that defaults to off is a
    flag, one whose default is "unset" takes on or off; a list is repeatable; a nested model is
    given as JSON."""
    from kgs_core.schema import choices

    for name, field in model.model_fields.items():
        kind = _optional(field.annotation)
        allowed = choices(kind)
        help_ = (
            (field.description or "")
            + (extra_help or {}).get(name, "")
            + ("" if field.is_required() or field.default in (None, False) or field.default == [] else f" (default {field.default})")
        )
        listed = "{" + ",".join(map(str, allowed)) + "}" if allowed else None
        if name in positional:
            p.add_argument(name, nargs="?", default=argparse.SUPPRESS, help=help_, metavar=listed or name.upper())
            continue
        flag = (flags or {}).get(name, "--" + name.replace("_", "-"))
        if kind is bool and field.default is False:
            p.add_argument(flag, dest=name, action="store_true", default=argparse.SUPPRESS, help=help_)
        elif kind is bool:
            p.add_argument(flag, dest=name, default=argparse.SUPPRESS, metavar="{on,off}", help=help_)
        elif typing.get_origin(kind) is list:
            p.add_argument(
                flag,
                dest=name,
                action="append",
                default=argparse.SUPPRESS,
                help=help_ + " (repeatable)",
                metavar=(metavars or {}).get(name),
            )
        else:
            nested = isinstance(kind, type) and issubclass(kind, BaseModel)
            p.add_argument(
                flag,
                dest=name,
                default=argparse.SUPPRESS,
                required=field.is_required(),
                metavar=listed or ("JSON" if nested else None),
                help=help_,
            )


def options_from(args: argparse.Namespace, model: type[BaseModel]):
    """The `model` the arguments `add_options` added describe; a bad value is a ValueError with
    the message the server's 422 gives (`kgs-app` exits with status 2 on it)."""
    from kgs_core.job_options import first_error

    given = {name: getattr(args, name) for name in model.model_fields if hasattr(args, name)}
    for name, value in given.items():
        kind = _optional(model.model_fields[name].annotation)
        if isinstance(kind, type) and issubclass(kind, BaseModel) and isinstance(value, str):
            try:
                given[name] = json.loads(value)
            except json.JSONDecodeError as exc:
                raise ValueError(f"{name}: not JSON ({exc.msg})") from None
    try:
        return model.model_validate(given)
    except ValidationError as exc:
        raise ValueError(first_error(exc)) from None
