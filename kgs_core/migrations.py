"""Every change to a saved layout, in one place: run.json (`migrate_run_json`), its training
configuration (`config`, `migrate_config`), the model configuration (`config.model`, model.pt's
`config`, `migrate_model_config`) and a saved model (model.pt, checkpoints:
`migrate_saved_model`), read back whatever version wrote them.

run.json carries `format_version`; each configuration `config_version` from version 1 on (a
dict without one is version 0, every run saved before the number existed). Each function steps
a dict through the upgrades from its version to the current one; each upgrade says what
changed. To change a layout: add a step below and bump the version.
"""

from __future__ import annotations

CONFIG_VERSION = 3
RUN_FORMAT_VERSION = 2

# Where the densification settings were before they became `TrainConfig.densify`.
FLAT_DENSIFY = {
    "grad_threshold": "grad_threshold",
    "densify_from": "start",
    "densify_until": "stop",
    "densify_every": "every",
    "prune_opacity": "prune_opacity",
    "percent_dense": "percent_dense",
    "opacity_reset_at": "opacity_reset_at",
    "max_gaussians": "max_gaussians",
}


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
    d.setdefault("tau_auto", False)  # runs saved before it decomposed at their configured τ
    return d


# Version 2 named the static/dynamic split "decompose" and the temporal variance K, as the
# paper does; old names, new names.
DECOMPOSE_RENAMES = {
    "split_in_place": "decompose_in_place",
    "resplit_to_dynamic": "redecompose_to_dynamic",
    "flow_split_share": "flow_vote_share",
    "flow_split_method": "flow_vote_method",
}
MODEL_RENAMES = {"variance_times": "K_times"}
ABLATION_RENAMES = {"split": "decompose"}
STATE_RENAMES = {"variance": "K"}  # per-Gaussian fields of a saved model
RUN_JSON_RENAMES = {"flow_split": "flow_vote", "split_note": "decomposition_note"}


def _renamed(d: dict, renames: dict) -> dict:
    return {renames.get(k, k): v for k, v in d.items()}


def _model_v1_to_v2(d: dict) -> dict:
    return _renamed(d, MODEL_RENAMES)


def _config_v1_to_v2(d: dict) -> dict:
    d = _renamed(d, DECOMPOSE_RENAMES)
    if isinstance(d.get("ablate"), (list, tuple)):
        d["ablate"] = [ABLATION_RENAMES.get(a, a) for a in d["ablate"]]
    return d


def _model_v2_to_v3(d: dict) -> dict:
    return d  # (version 3 changed the training configuration only)


def _config_v2_to_v3(d: dict) -> dict:
    # Before tau_auto_from, Otsu's split read every Gaussian's K.
    return {"tau_auto_from": 0.0, **d}


MODEL_STEPS = [_model_v0_to_v1, _model_v1_to_v2, _model_v2_to_v3]  # MODEL_STEPS[v] upgrades a version-v model config to v + 1
CONFIG_STEPS = [_config_v0_to_v1, _config_v1_to_v2, _config_v2_to_v3]
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
    for step in MODEL_STEPS[_version(d, "model") :]:
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


def _model_version(state: dict) -> int:
    """The layout version of a saved model state: its model configuration's (a state is saved
    with its configuration); a config without a number is version 0."""
    config = state.get("config")
    version = config.get("config_version", 0) if isinstance(config, dict) else CONFIG_VERSION
    return version if isinstance(version, int) else CONFIG_VERSION


def migrate_saved_model(saved: dict) -> dict:
    """model.pt or a checkpoint (`{"model": state, "levels": [snapshot, ...], ...}`) in the
    current layout: the model's and every level snapshot's per-Gaussian fields under their
    current names, and a checkpoint's copy of run.json's records. The one place a saved model
    is upgraded: `KinematicsGS.from_state` reads the current layout."""
    model = saved.get("model")
    if not isinstance(model, dict) or _model_version(model) >= 2:
        return saved
    levels = saved.get("levels")
    return {
        **_renamed(saved, RUN_JSON_RENAMES),
        "model": _renamed(model, STATE_RENAMES),
        "levels": [_renamed(s, STATE_RENAMES) if isinstance(s, dict) else s for s in levels] if isinstance(levels, list) else levels,
    }


def migrate_run_json(info: dict, where: str = "run.json") -> dict:
    """A run.json of any format version in the current layout: its keys renamed, its `config`
    migrated (`migrate_config`) and stamped with the current version; ValueError naming `where`
    for a version this code does not know."""
    version = info.get("format_version")
    if not isinstance(version, int) or isinstance(version, bool) or not 1 <= version <= RUN_FORMAT_VERSION:
        raise ValueError(f"{where}: run format {version!r} not supported (expected 1..{RUN_FORMAT_VERSION})")
    out = _renamed(info, RUN_JSON_RENAMES) if version < 2 else dict(info)
    out["format_version"] = RUN_FORMAT_VERSION
    if isinstance(out.get("config"), dict):
        config = migrate_config(out["config"])
        if isinstance(config.get("model"), dict):
            config["model"] = {"config_version": CONFIG_VERSION, **config["model"]}
        out["config"] = {"config_version": CONFIG_VERSION, **config}
    return out


def renamed_setting(key: str) -> str | None:
    """The current name of a setting an older version called `key` (`model.` prefix kept)."""
    prefix, _, name = key.rpartition(".")
    new = (MODEL_RENAMES if prefix == "model" else DECOMPOSE_RENAMES).get(name)
    return None if new is None else f"{prefix}.{new}" if prefix else new
