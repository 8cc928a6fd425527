"""argparse types of the `kgs-app` command line: training settings (`--set KEY=VALUE` and the
named ones) checked against the training schema, switches and counts."""

from __future__ import annotations

import argparse


def setting(text: str) -> tuple[str, object]:
    """argparse type: KEY=VALUE of a training setting (`parse_setting`)."""
    from kgs_core.train.settings import parse_setting

    try:
        return parse_setting(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def on_off(text: str) -> bool:
    """argparse type: a switch, on or off."""
    if text not in ("on", "off"):
        raise argparse.ArgumentTypeError(f"expected on or off, got {text!r}")
    return text == "on"


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (an iteration count)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def add_named_settings(p: argparse.ArgumentParser) -> None:
    """`--NAME` for each setting offered by name (`settings.NAMED`), its type, choices and
    bounds read from the schema: a word setting takes its choices, a switch on/off."""
    from kgs_core.schema import choices
    from kgs_core.train.settings import NAMED, setting_type

    def typed(name, kind):
        def convert(text: str):
            try:
                value = (NAMED[name].parse or kind)(text)
            except ValueError as exc:
                raise argparse.ArgumentTypeError(str(exc) if NAMED[name].parse else f"expected "
                                                 f"{'a whole number' if kind is int else 'a number'}, got {text!r}") from None
            try:
                return NAMED[name].check(value)
            except ValueError as exc:
                raise argparse.ArgumentTypeError(str(exc)) from None
        return convert

    for name, named in NAMED.items():
        kind = setting_type(named.key)
        flag = "--" + name.replace("_", "-")
        if kind is bool:
            p.add_argument(flag, type=on_off, metavar="{on,off}", help=named.help)
        elif choices(kind) is not None:
            p.add_argument(flag, choices=choices(kind), help=named.help)
        else:
            p.add_argument(flag, type=typed(name, kind), help=named.help)
