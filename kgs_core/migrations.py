"""Every change to a saved layout, in one place: a run's training configuration (run.json's
`config`) and its model configuration (run.json's `config.model`, model.pt's `config`), read
back whatever version wrote them.

Each layout carries `config_version` from version 1 on; a dict without one is version 0 (every
run saved before the number existed). `migrate_config` and `migrate_model_config` step a dict
through the upgrades from its version to the current one; each upgrade says what changed. To
change a layout: add a step below and bump CONFIG_VERSION.
"""

from __future__ import annotations

CONFIG_VERSION = 1

# Where the densification settings were before they became `TrainConfig.densify`.
FLAT_DENSIFY = {"grad_threshold": "grad_threshold", "densify_from": "start", "densify_until": "stop",
                "densify_every": "every", "prune_opacity": "prune_opacity", "percent_dense": "percent_dense",
                "opacity_reset_at": "opacity_reset_at", "max_gaussians": "max_gaussians"}


def _model_v0_to_v1(d: dict) -> dict:
    # Runs saved before kr_form existed all used the paper's form: keep rendering them so; before
    # knn_radius, C.F. averaged over unbounded neighbourhoods; before spawned_motion, spawned
    # Gaussians followed the field.
    return {"kr_form": "paper", "knn_radius": 0.0, "spawned_motion": "field", **d}


def _config_v0_to_v1(d: dict) -> dict:
    d = dict(d)
    if "densify" not in d:  # the densification settings at the top level
        d["densify"] = {new: d.pop(old) for old, new in FLAT_DENSIFY.items() if old in d}
    if isinstance(d.get("camera_blur"), bool):  # when it was an on/off switch
        d["camera_blur"] = "poses" if d["camera_blur"] else "off"
    d.setdefault("tau_auto", False)  # runs saved before it split at their configured τ
    return d


MODEL_STEPS = [_model_v0_to_v1]  # MODEL_STEPS[v] upgrades a version-v model config to v + 1
CONFIG_STEPS = [_config_v0_to_v1]
assert len(MODEL_STEPS) == len(CONFIG_STEPS) == CONFIG_VERSION


def _version(d: dict, what: str) -> int:
    version = d.pop("config_version", 0)
    if not isinstance(version, int) or isinstance(version, bool) or not 0 <= version <= CONFIG_VERSION:
        raise ValueError(f"{what}.config_version must be a whole number in 0..{CONFIG_VERSION}, got {version!r}")
    return version


def migrate_model_config(d: dict) -> dict:
    """A model configuration dict (`ModelConfig.to_dict`) of any version, in the current layout
    and without its version number."""
    d = dict(d)
    for step in MODEL_STEPS[_version(d, "model"):]:
        d = step(d)
    return d


def migrate_config(d: dict) -> dict:
    """A training configuration dict (`TrainConfig.to_dict`) of any version, its `model` block
    included, in the current layout and without version numbers."""
    d = dict(d)
    version = _version(d, "config")
    for step in CONFIG_STEPS[version:]:
        d = step(d)
    if isinstance(d.get("model"), dict):
        model = dict(d["model"])
        model.setdefault("config_version", version)  # the model block was written with the config
        d["model"] = migrate_model_config(model)
    return d
