"""Training settings by key, as the command line and the server take them.

Every field of the schema (`TrainConfig`, and `model.FIELD` / `densify.FIELD` of its nested
parts) is a setting; `parse_setting` reads `KEY=VALUE` of any of them, checked against the
field's type. A few are also offered by name (`NAMED`: `kgs-app train --tau`, the REST
`TrainRequest.tau`); the command line and the server build those options from this table and
the schema's types, so neither keeps a copy, and `named_overrides` turns their values into
`make_config` overrides.
"""

from __future__ import annotations

import json
import types
from dataclasses import MISSING, dataclass, fields
from functools import cache
from typing import Union, get_args, get_origin

from ..schema import choices, field_types
from .config import NESTED, TrainConfig

# Fields that are not settings: the ablations have their own option, `fitted` is an output.
NOT_SETTINGS = ("ablate", "fitted")


@dataclass(frozen=True)
class NamedSetting:
    """A setting offered by name; `key` is its place in the schema, the bounds are inclusive
    unless `positive` (a number above 0)."""

    key: str
    help: str
    minimum: float | None = None
    maximum: float | None = None
    positive: bool = False

    def check(self, value):
        """`value`, or ValueError when it is out of bounds."""
        if value is None:
            return value
        if self.positive and not value > 0:
            raise ValueError(f"must be above 0, got {value!r}")
        if self.minimum is not None and value < self.minimum:
            raise ValueError(f"must be at least {self.minimum}, got {value!r}")
        if self.maximum is not None and value > self.maximum:
            raise ValueError(f"must be at most {self.maximum}, got {value!r}")
        return value


NAMED: dict[str, NamedSetting] = {
    "iterations": NamedSetting("iterations", "override the preset's iteration count (its schedule scales with it)",
                               minimum=1, maximum=1_000_000),
    "seed": NamedSetting("seed", "training seed", minimum=0, maximum=2**31 - 1),
    "tau": NamedSetting("model.tau", "static/dynamic threshold on the temporal variance K (normalised scene units^2; "
                        "default: fitted to the scene, an RMS image motion of 0.62 px)", positive=True),
    "exposure": NamedSetting("exposure", "the training video's exposure, a fraction of the frame interval (default: the "
                             "scene's; ingest assumes 0.5). 0 turns the kinematic blur (K.R.) off", minimum=0, maximum=1),
    "velocity": NamedSetting("model.velocity", "velocity estimate of the kinematic basis"),
    "basis": NamedSetting("model.basis", "kinematic frame: the paper's (reference-axis switch), branch-free, or "
                          "continuous (principal)"),
    "kr_form": NamedSetting("model.kr_form", "kinematic refinement: the paper's projection onto the velocity frame, or "
                            "the predicted covariance convolved with the motion during the exposure (docs/method.md)"),
    "camera_blur": NamedSetting("camera_blur", "also blur every Gaussian along the camera's own motion during the "
                                "exposure (hand-held shake): from the poses' differences, or learned per frame from "
                                "there (default off; docs/method.md)"),
    "pose_refine": NamedSetting("pose_refine", "fit a rigid correction of each training camera's pose, for footage "
                                "whose structure-from-motion poses are poor (default off; docs/real-footage.md)"),
    "on_nonfinite": NamedSetting("on_nonfinite", "NaN/Inf in training: stop with an error naming the tensor (default), "
                                 "or restore the last good checkpoint and continue with a lower learning rate"),
}


@cache
def schema() -> dict[str, tuple[object, object]]:
    """{KEY: (its type, its default)} of every setting."""
    out = {}
    for prefix, cls in (("", TrainConfig), *((f"{part}.", part_cls) for part, part_cls in NESTED.items())):
        hints = field_types(cls)
        for f in fields(cls):
            if not prefix and f.name in (*NOT_SETTINGS, *NESTED):
                continue
            default = f.default if f.default is not MISSING else f.default_factory()
            out[prefix + f.name] = (hints[f.name], default)
    return out


def setting_type(key: str):
    """The type of setting `key` with an optional `X | None` unwrapped to X (the None is a
    default, not a value anyone sets)."""
    annotation = schema()[key][0]
    if get_origin(annotation) in (Union, types.UnionType):
        annotation = next(a for a in get_args(annotation) if a is not type(None))
    return annotation


def parse_setting(text: str) -> tuple[str, object]:
    """`KEY=VALUE` of one training setting, checked against the schema: KEY a `TrainConfig`
    field, `model.<ModelConfig field>` or `densify.<DensifyStrategy field>`; VALUE as JSON when
    it parses (numbers, true/false, lists), else the plain string, and of the field's type, so
    that a mistyped value fails here and not minutes into training (an integer stands for a
    float; true/false only for a switch; a word only among its choices). Raises ValueError
    naming the key. What `kgs-app train --set`, the REST `settings` and `bench quality`'s
    `@KEY=VALUE` read."""
    key, eq, raw = text.partition("=")
    known = schema()
    if not eq or key not in known:
        raise ValueError(f"{text!r} is not KEY=VALUE with KEY a training setting (e.g. noise_init_frames, model.tau)")
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    value = tuple(value) if isinstance(value, list) else value
    default = known[key][1]
    want, allowed = setting_type(key), choices(setting_type(key))
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    ok = (value is None and default is None) or (
        value in allowed if allowed is not None else
        isinstance(value, bool) if want is bool else
        number if want is float else
        isinstance(value, want) and not isinstance(value, bool))
    if not ok and allowed is not None:
        raise ValueError(f"{key} must be one of {', '.join(allowed)}, got {raw!r}")
    if not ok:
        kind = ({bool: "true or false", float: "a number", int: "a whole number", str: "a word",
                 tuple: "a JSON list"}.get(want, getattr(want, "__name__", str(want))))
        raise ValueError(f"{key} takes {kind} (default {default!r}), got {raw!r}")
    return key, float(value) if want is float and value is not None else value


def named_overrides(values: dict) -> dict:
    """`make_config` overrides from {name in NAMED: value}; None (not given) is left out."""
    return {NAMED[name].key: value for name, value in values.items() if name in NAMED and value is not None}
