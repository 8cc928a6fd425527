"""The run directory: everything a training run produces, loadable without the training code.

```
RUN/
  run.json            format version, scene path, config, status, counts, timings
  model.pt            the final model (KinematicsGS.state() + LoD level snapshots)
  checkpoints/        ckpt_XXXXXX.pt: model + optimizer + schedule state, for --resume
  log.csv             iteration, train_seconds, wall_seconds, loss, psnr_heldout, psnr_heldout_dynamic
                      (inside the ground-truth dynamic masks, when the scene has them), gaussians,
                      dynamic_share, exposure (the one K.R. trains with; it moves with fit_exposure)
  psnr_vs_time.png    held-out PSNR (and inside the dynamic mask) against training time
  decomposition.npy   temporal variance K per Gaussian (final level)
  metrics.json/.md    written by `kgs-app eval`
  error.txt           present when training failed
```
(docs/run-directory.md has the rest: edits.json, exports/, progress.json, the keys of run.json.)
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .device import tensors_to
from .io import atomic_write_bytes, atomic_write_text
from .migrations import RUN_FORMAT_VERSION, migrate_run_json, migrate_saved_model
from .model.dynamic import KinematicsGS


class RunError(ValueError):
    pass


def save_torch(path: Path, obj) -> None:
    buf = io.BytesIO()
    torch.save(obj, buf)
    atomic_write_bytes(path, buf.getvalue())


def load_torch(path: Path):
    """A model or checkpoint written by `save_torch`, read with `weights_only=True`: tensors,
    numbers, strings and containers only. A pickle can run any code while it loads, and a run
    folder may come from anyone (an upload, a copied workspace), so nothing here is unpickled."""
    return torch.load(path, map_location="cpu", weights_only=True)


def write_run_json(run_dir: Path, info: dict) -> None:
    atomic_write_text(run_dir / "run.json", json.dumps({"format_version": RUN_FORMAT_VERSION, **info}, indent=1))


def read_run_json(run_dir: Path) -> dict:
    path = Path(run_dir) / "run.json"
    if not path.is_file():
        raise RunError(f"not a run directory (no run.json): {run_dir}")
    try:
        info = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise RunError(f"{path}: invalid JSON ({exc.msg})") from None
    if not isinstance(info, dict):
        raise RunError(f"{path}: must be a JSON object")
    try:
        return migrate_run_json(info, str(path))
    except ValueError as exc:
        raise RunError(str(exc)) from None


def learned_blur(info: dict) -> dict:
    """What a run's "as captured" render can show, from its run.json `info`: `objects` (K.R.'s
    blur along each moving Gaussian's motion acts), `camera` (the camera's own motion within
    the exposure was modelled: "off", "poses" or "learned"), `note`, a sentence for the viewer
    beside its exposure control, and `camera_motion`, the learned shake per training frame
    (`train/camera_motion.py: camera_motion_records`) where the run kept it."""
    from .evaluate import KR_MIN_GAIN_DB

    cfg = info.get("config") or {}
    exposure = float(info.get("exposure") or 0.0)
    camera = str(cfg.get("camera_blur") or "off")
    kinematic = (cfg.get("model") or {}).get("kinematic", True) and "kr" not in (cfg.get("ablate") or ())
    check, effect = info.get("kr_check"), info.get("kr_effect")
    if exposure <= 0:
        return {"objects": False, "camera": camera, "note": "trained at exposure 0: no blur was modelled"}
    if not kinematic or "decompose" in (cfg.get("ablate") or ()) or "deform" in (cfg.get("ablate") or ()):
        return {"objects": False, "camera": camera, "note": "trained without K.R.: no motion blur was modelled"}
    measured = check if check is not None else effect
    if check is not None and not check.get("kept", True):
        objects = False
        why = (
            f"K.R. was turned off at iteration {check.get('iteration')}: its blur changed "
            f"{check.get('changed_share', 0):.1%} of the training pixels visibly"
        )
    elif measured is not None and measured.get("gain_db", 0.0) < KR_MIN_GAIN_DB:
        objects = False
        why = f"K.R.'s blur changes {measured.get('changed_share', 0):.1%} of the training pixels visibly"
    else:
        objects = True
        why = "blur along each moving Gaussian's motion within the exposure (K.R.)"
        if measured is not None:
            why += f", visible in {measured.get('changed_share', 0):.1%} of the training pixels"
    records = info.get("camera_motion") if camera != "off" else None
    if camera == "off":
        cam = "the camera's own shake is not modelled (train with --camera-blur learned)"
    elif records:
        cam = f"the camera's own shake ({camera}) at the training frame nearest in time, applied to the whole scene"
    else:
        cam = "the camera's own shake was modelled, but this run did not keep it (trained before runs saved it)"
    if objects:
        note = f"shows the learned {why}" + (f", and {cam}" if records else f"; {cam}")
    elif records:
        note = f"shows {cam}; {why}"
    else:
        note = f"next to no learned blur; {why}; {cam}"
    out = {"objects": objects, "camera": camera, "note": f"exposure {exposure:.2f}: {note}"}
    if records:
        out["camera_motion"] = records
    return out


@dataclass
class LoadedRun:
    path: Path
    info: dict
    model: KinematicsGS
    levels: list[dict]  # LoD snapshots, coarse to fine; the model itself is the finest

    @property
    def static_only(self) -> bool:
        """Trained without deformation (`--ablate deform`): render the canonical Gaussians."""
        return "deform" in (self.info.get("config", {}).get("ablate") or ())

    def scene_path(self) -> Path:
        """The training scene: relative to the run first (`scene_from_run`: a copied or moved
        workspace reads its own copy, not the original), then as recorded, then in the run's
        workspace (runs written before either was stored, or a workspace that moved)."""
        recorded = Path(self.info.get("scene", ""))
        candidates = [self.path / self.info["scene_from_run"]] if self.info.get("scene_from_run") else []
        candidates += [recorded] if recorded.is_absolute() else [recorded, self.path.parent.parent.parent / recorded]
        candidates.append(self.path.parent.parent / "scenes" / recorded.name)
        for c in candidates:
            if (c / "scene.json").is_file() or c.is_dir():
                return c
        raise RunError(f"{self.path}/run.json: scene {recorded} not found (pass the scene folder explicitly)")

    @property
    def n_levels(self) -> int:
        return len(self.levels) + 1

    def level(self, level: int) -> KinematicsGS:
        """The model at LoD `level` (1 = coarsest, n_levels = the final one)."""
        if not 1 <= level <= self.n_levels:
            raise RunError(f"LoD level must be in 1..{self.n_levels}, got {level}")
        if level == self.n_levels:
            return self.model
        return level_view(self.model, self.levels[level - 1])


def level_view(model: KinematicsGS, snap: dict) -> KinematicsGS:
    """A model sharing the networks of `model` with a level snapshot's Gaussians."""
    from .model.gaussians import GaussianParams
    from .model.neighbours import checked_knn
    from .model.per_gaussian import PerGaussian

    # Everything of the model's (its config and every network, whichever it has) is shared; the
    # per-Gaussian state below is the snapshot's. The view is a fresh Module (its own hook and
    # module tables), so that giving it its own Gaussians leaves the model's alone.
    view = KinematicsGS.__new__(KinematicsGS)
    torch.nn.Module.__init__(view)
    view.__dict__.update({k: v for k, v in model.__dict__.items() if k not in view.__dict__})
    view._modules.update(model._modules)
    view._parameters.update(model._parameters)
    view._buffers.update(model._buffers)
    view.training = model.training  # as its (shared) networks are: Module.__init__ set it to True
    view.params = GaussianParams(**snap["params"])
    view.decomposed = model.decomposed
    view.per_gaussian = PerGaussian.from_state(snap, len(view.params))  # its own: the model's stays the model's
    view.min_scale = snap["min_scale"]
    # The graph the level trained with (snapshots from before it was kept: rebuilt).
    view._knn = checked_knn(snap.get("knn"), int(view.dynamic.sum()))
    view._knn_mean = None
    return view


def load_run(run_dir: str | Path, device: torch.device | None = None) -> LoadedRun:
    """The run's final model (and its LoD snapshots) on `device` (the CPU when None); build it
    inside `device.computing_on` for a GPU, so that its own tensors land there too."""
    run_dir = Path(run_dir)
    info = read_run_json(run_dir)
    path = run_dir / "model.pt"
    if not path.is_file():
        raise RunError(f"{run_dir}: no model.pt (training not finished? status: {info.get('status')})")
    try:
        state = load_torch(path)
    except Exception as exc:
        raise RunError(f"{path}: cannot load ({exc})") from None
    if not isinstance(state, dict):
        raise RunError(f"{path}: malformed model file (not a dict)")
    state = migrate_saved_model(state)
    if device is not None:
        state = tensors_to(state, device)
    try:
        model = KinematicsGS.from_state(state["model"])
    except (KeyError, TypeError, ValueError, RuntimeError) as exc:
        raise RunError(f"{path}: malformed model state ({type(exc).__name__}: {exc})") from None
    model.eval()
    return LoadedRun(run_dir, info, model, state.get("levels", []))


def read_log(run_dir: Path) -> list[dict]:
    path = Path(run_dir) / "log.csv"
    if not path.is_file():
        return []
    lines = path.read_text().strip().splitlines()
    head = lines[0].split(",")
    rows = []
    for line in lines[1:]:
        vals = line.split(",")
        rows.append({k: (float(v) if v not in ("", "nan") else float("nan")) for k, v in zip(head, vals)})
    return rows


def save_decomposition(run_dir: Path, K: torch.Tensor) -> None:
    buf = io.BytesIO()
    np.save(buf, K.detach().cpu().numpy().astype(np.float32))
    atomic_write_bytes(run_dir / "decomposition.npy", buf.getvalue())
