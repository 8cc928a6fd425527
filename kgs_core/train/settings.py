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
import math
import types
from collections.abc import Callable
from dataclasses import MISSING, dataclass, fields
from functools import cache
from typing import Union, get_args, get_origin

from ..schema import choices, field_types
from .budget import parse_duration
from .config import NESTED, TrainConfig

# Fields that are not settings: the ablations have their own option, `fitted` is an output,
# and `init_from` is a path, which a request names by run id (POST /api/runs's `init_from_run`,
# `kgs-app train --init-from`): no setting reaches a file on the server.
NOT_SETTINGS = ("ablate", "fitted", "init_from", "budget_pilot")


@dataclass(frozen=True)
class Bound:
    """The values a numeric setting (or each element of a list setting) may take: `low` to
    `high` inclusive, `low` excluded when `above`; lists hold at most `length` elements."""

    low: float
    high: float
    above: bool = False
    length: int = 16

    def check(self, key: str, value) -> None:
        for v in value if isinstance(value, tuple) else (value,):
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ValueError(f"{key} takes numbers, got {v!r}")
            if not math.isfinite(v):
                raise ValueError(f"{key} must be a finite number, got {v!r}")
            if (v <= self.low if self.above else v < self.low) or v > self.high:
                low = f"above {_number(self.low)}" if self.above else f"at least {_number(self.low)}"
                raise ValueError(f"{key} must be {low} and at most {_number(self.high)}, got {v!r}")
        if isinstance(value, tuple) and len(value) > self.length:
            raise ValueError(f"{key} takes at most {self.length} values, got {len(value)}")


def _number(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else f"{x:g}"


FRACTION = Bound(0, 1)
# What a setting not listed in BOUNDS may take: whole numbers are counts and schedule points,
# other numbers weights, rates and lengths; none negative, none unbounded.
COUNT, AMOUNT = Bound(0, 2**31 - 1), Bound(0, 1e6)
# The bounds that differ: sizes that set memory and time (a request must not ask for a
# machine's worth), fractions, and the few settings that may be negative or must be positive.
BOUNDS: dict[str, Bound] = {
    "iterations": Bound(1, 1_000_000),
    "time_budget": Bound(0, 7 * 24 * 3600),
    "batch_size": Bound(1, 16),
    "downscales": Bound(0, 4),
    "seed": Bound(0, 2**31 - 1),
    "init_points": Bound(1, 1_000_000),
    "densify.max_gaussians": Bound(1, 5_000_000),
    "coarse_factor": Bound(1, 64),
    "spawn_frames": Bound(0, 1000),
    "spawn_max": Bound(1, 100_000),
    "spawn_life": Bound(0, 1000, above=True),
    "lod_levels": Bound(1, 8),
    "lod_fractions": Bound(0, 1, above=True, length=8),
    "lod_rho": Bound(0, 1, above=True),
    "lod_importance_views": Bound(1, 1000),
    "eval_every": Bound(1, 2**31 - 1),
    "eval_frames": Bound(1, 1000),
    "checkpoint_every": Bound(1, 2**31 - 1),
    "nonfinite_max_restores": Bound(0, 100),
    "nonfinite_lr_factor": Bound(0, 1, above=True),
    "reg_static_samples": Bound(0, 1_000_000),
    "densify.opacity_reset_at": Bound(0, 2**31 - 1, length=100),
    "densify.every": Bound(1, 2**31 - 1),
    "model.sh_degree": Bound(0, 3),
    "model.feature_dim": Bound(1, 256),
    "model.knn": Bound(1, 64),
    "model.K_times": Bound(2, 256),
    "model.deform_spatial": Bound(2, 512),
    "model.deform_temporal": Bound(1, 1024),
    "model.deform_features": Bound(1, 256),
    "model.deform_multires": Bound(1, 16, length=4),
    "model.deform_width": Bound(1, 1024),
    "model.deform_depth": Bound(0, 8),
    "model.tau": Bound(0, 1e6, above=True),
    "model.kappa_init": Bound(-1e3, 1e3),
    "model.bound": Bound(0, 1e6, above=True),
    **{
        key: FRACTION
        for key in (
            "exposure",
            "downscale_until",
            "spawn_from",
            "noise_until",
            "noise_delay",
            "noise_w_delay",
            "frame_sampling_mix",
            "time_window_start",
            "lod_prune_importance",
            "kr_check_at",
            "flow_vote_share",
            "tau_auto_from",
            "densify.prune_opacity",
            "densify.percent_dense",
        )
    },
}


def bound(key: str) -> Bound | None:
    """The bounds of setting `key`; None for a word or a switch."""
    kind = setting_type(key)
    if kind is bool or choices(kind) is not None or kind is str:
        return None
    if key in BOUNDS:
        return BOUNDS[key]
    default = schema()[key][1]
    whole = kind is int or (kind is tuple and all(isinstance(v, int) for v in default))
    return COUNT if whole else AMOUNT


def check_setting(key: str, value):
    """`value`, or ValueError naming `key` when it is out of the setting's bounds (NaN and
    ±inf included): what every way of giving a setting (`--set`, `--tau`, the REST body,
    `bench quality`'s `@KEY=VALUE`, `make_config`) goes through."""
    limits = bound(key)
    if limits is not None and value is not None:
        limits.check(key, value)
    return value


def check_config(cfg: TrainConfig) -> TrainConfig:
    """`cfg`, or ValueError naming the first setting out of its bounds."""
    for key in schema():
        part, _, name = key.rpartition(".")
        check_setting(key, getattr(getattr(cfg, part) if part else cfg, name))
    return cfg


@dataclass(frozen=True)
class NamedSetting:
    """A setting offered by name; `key` is its place in the schema, its bounds are the
    setting's (`bound`)."""

    key: str
    help: str
    # How the command line reads the value (None: the schema's type).
    parse: Callable[[str], object] | None = None

    def check(self, value):
        """`value`, or ValueError when it is out of bounds."""
        return check_setting(self.key, value)


NAMED: dict[str, NamedSetting] = {
    "iterations": NamedSetting("iterations", "override the preset's iteration count (its schedule scales with it)"),
    "time_budget": NamedSetting(
        "time_budget",
        "train within this time on this machine, e.g. 10m or 600 (seconds): a "
        "short pilot picks the iterations and Gaussian budget that fit, recorded in run.json "
        "(default: 3.5 s a frame for a video ingest at full size, else none: the preset's schedule)",
        parse=parse_duration,
    ),
    "seed": NamedSetting("seed", "training seed"),
    "tau": NamedSetting(
        "model.tau",
        "static/dynamic threshold on the temporal variance K (normalised scene units^2; "
        "default: fitted to the scene, an RMS image motion of 0.62 px)",
    ),
    "exposure": NamedSetting(
        "exposure",
        "the training video's exposure, a fraction of the frame interval (default: the "
        "scene's; ingest assumes 0.5). 0 turns the kinematic blur (K.R.) off",
    ),
    "velocity": NamedSetting("model.velocity", "velocity estimate of the kinematic basis"),
    "basis": NamedSetting("model.basis", "kinematic frame: the paper's (reference-axis switch), branch-free, or continuous (principal)"),
    "kr_form": NamedSetting(
        "model.kr_form",
        "kinematic refinement: the paper's projection onto the velocity frame, or "
        "the predicted covariance convolved with the motion during the exposure (docs/method.md)",
    ),
    "camera_blur": NamedSetting(
        "camera_blur",
        "also blur every Gaussian along the camera's own motion during the "
        "exposure (hand-held shake): from the poses' differences, or learned per frame from "
        "there (default: learned where the training camera draws a streak of 0.5 px or "
        "more during the exposure, else off; docs/method.md)",
    ),
    "pose_refine": NamedSetting(
        "pose_refine",
        "fit a rigid correction of each training camera's pose, for footage "
        "whose structure-from-motion poses are poor (default off; docs/real-footage.md)",
    ),
    "device": NamedSetting(
        "device",
        "where to train: auto takes CUDA when torch sees a GPU (the rasteriser is then gsplat's: "
        "pip install 'kinematics-gs[cuda]'), else the CPU",
    ),
    "on_nonfinite": NamedSetting(
        "on_nonfinite",
        "NaN/Inf in training: stop with an error naming the tensor (default), "
        "or restore the last good checkpoint and continue with a lower learning rate",
    ),
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
        from ..migrations import renamed_setting

        hint = f" ({key} is now called {renamed_setting(key)})" if eq and renamed_setting(key) else ""
        raise ValueError(f"{text!r} is not KEY=VALUE with KEY a training setting (e.g. noise_init_frames, model.tau){hint}")
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    value = tuple(value) if isinstance(value, list) else value
    default = known[key][1]
    want, allowed = setting_type(key), choices(setting_type(key))
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    ok = (value is None and default is None) or (
        value in allowed
        if allowed is not None
        else isinstance(value, bool)
        if want is bool
        else number
        if want is float
        else isinstance(value, want) and not isinstance(value, bool)
    )
    if not ok and allowed is not None:
        raise ValueError(f"{key} must be one of {', '.join(allowed)}, got {raw!r}")
    if not ok:
        kind = {bool: "true or false", float: "a number", int: "a whole number", str: "a word", tuple: "a JSON list"}.get(
            want, getattr(want, "__name__", str(want))
        )
        raise ValueError(f"{key} takes {kind} (default {default!r}), got {raw!r}")
    value = float(value) if want is float and value is not None else value
    return key, check_setting(key, value)


def named_overrides(values: dict) -> dict:
    """`make_config` overrides from {name in NAMED: value}; None (not given) is left out."""
    return {NAMED[name].key: NAMED[name].check(value) for name, value in values.items() if name in NAMED and value is not None}
