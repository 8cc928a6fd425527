"""A run loaded for viewing (`RunView`): the model at each LoD, the live τ, the edit layer, and
the static and dynamic sets packed as splat buffers (`splat_buffer`). Used by the server and
the desktop viewer alike.

The static set is packed once per LoD (and again after a τ change or an edit); a time change
packs only the dynamic set, interpolated from `Trajectories` once they are built."""

from __future__ import annotations

import atexit
import copy
import threading
from pathlib import Path

import numpy as np
import torch

from .edits import EditLayer, load_edits, save_edits
from .export.bake import Baked, baked_from
from .model.decomposition import K_histogram, decomposition_counts
from .model.gaussians import presence
from .run import LoadedRun, learned_blur, load_run
from .splat_buffer import F16_MAX, cov_scale, new_buffer, pack_buffer, pack_sh_buffer, rgba_of
from .train.camera_motion import nearest_camera_motion

_STOP = threading.Event()  # set at interpreter exit: builders stop between samples
_BUILDERS: set[threading.Thread] = set()


@atexit.register
def _stop_builders() -> None:
    """A daemon thread still inside torch when the interpreter tears down aborts the process
    ("terminate called without an active exception"): stop the builders and wait for them."""
    _STOP.set()
    for th in list(_BUILDERS):
        th.join(timeout=10)


class Trajectories:
    """The dynamic set sampled once per frame interval (positions, packed covariances,
    velocities), so that a time change is a linear interpolation between two samples instead of
    three deformation-field evaluations. Built in a background thread; exact evaluation answers
    until it is ready. Covariances interpolate linearly (a convex combination of SPD matrices
    stays SPD). The interpolation error is measured by `kgs-app bench serve` (docs/serve.md).

    The cache belongs to one version of the view (τ and edits), so the Gaussians the edits keep
    are fixed for its life: `buffer` cuts the samples to them once (`_kept`), and each request
    then only interpolates and packs."""

    def __init__(self, view: "RunView", model, lod: int, version: int, exposure: float):
        self.key = (lod, version, exposure)
        self.view = view
        self.model = model
        self.ready = threading.Event()
        self.failed: str | None = None
        self.times = None
        self._kept_samples: dict | None = None
        self._kept_lock = threading.Lock()
        th = threading.Thread(target=self._build, daemon=True)
        _BUILDERS.add(th)
        th.start()

    @torch.no_grad()
    def _build(self) -> None:
        lod, version, exposure = self.key
        try:
            m = self.model
            n = max(2, int(round(1.0 / max(self.view.dt, 1e-3))) + 1)
            times = np.linspace(0.0, 1.0, n)
            means, covs, vels, sampled_opacities = [], [], [], []
            for t in times:
                if self.view.version != version or _STOP.is_set():
                    return  # superseded by a tau change or an edit, or shutting down
                # Not under `compute`: the build must not queue behind every client's exact
                # evaluation, or it never finishes while many clients scrub.
                idx, g = m.at_dynamic(float(t), exposure, self.view.dt)
                means.append(g.means.numpy())
                covs.append(g.covars6.numpy())
                vels.append(g.velocity.numpy())
                if m.time_opacity is not None:
                    sampled_opacities.append((m.params.opacities[idx] * m.opacity_factor(idx, float(t))).numpy())
            self.idx = idx.numpy()
            # With a time opacity, the opacities per sample (None without it), interpolated like
            # the means and only then quantised: its factor can raise an opacity, so scaling the
            # 8-bit alpha instead would lose a nearly transparent Gaussian it makes opaque.
            self.sampled_opacities = np.stack(sampled_opacities).astype(np.float32) if sampled_opacities else None
            self.means, self.cov6, self.vels = np.stack(means), np.stack(covs), np.stack(vels)
            # Opacities before the lifespan's presence factor, which `buffer` applies at its t
            # (exact, not interpolated: it is a narrow Gaussian in time).
            self.rgba = rgba_of(g.sh, m.params.opacities.detach()[idx])
            self.lifespan = m.lifespan[idx].numpy()
            self.times = times
            self.ready.set()
        except Exception as exc:  # keep serving exact evaluations
            self.failed = f"{type(exc).__name__}: {exc}"
        finally:
            _BUILDERS.discard(threading.current_thread())

    def _bracket(self, t: float) -> tuple[int, float]:
        """(k, w): `t` lies at weight w between samples k and k + 1."""
        times = self.times
        k = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2))
        return k, float((t - times[k]) / (times[k + 1] - times[k]))

    def _kept(self, keep: np.ndarray) -> dict:
        """The samples cut to the Gaussians `keep` (the view's edits at this cache's version),
        ready to interpolate straight into a buffer: covariances in one unit for the whole cache
        and clipped to float16's range, as are the velocities (a convex mix stays inside it);
        made on the first request."""
        with self._kept_lock:
            if self._kept_samples is None:
                sel = keep[self.idx]
                cut = (lambda a: a) if sel.all() else (lambda a: a[:, sel])  # noqa: E731
                cov6 = cut(self.cov6)
                scale = float(np.median([cov_scale(c) for c in cov6]))
                self._kept_samples = {
                    "means": torch.from_numpy(np.ascontiguousarray(cut(self.means))),
                    "scale": scale,
                    "cov6": torch.from_numpy(np.clip(cov6 / scale, -F16_MAX, F16_MAX, dtype=np.float32)),
                    "vels": torch.from_numpy(np.clip(cut(self.vels), -F16_MAX, F16_MAX, dtype=np.float32)),
                    "rgba": self.rgba[sel],
                    "index": self.idx[sel].astype(np.uint32),
                    "sampled_opacities": (
                        None if self.sampled_opacities is None else torch.from_numpy(np.ascontiguousarray(cut(self.sampled_opacities)))
                    ),
                    "lifespan": self.lifespan[sel],
                }
                self.means = self.cov6 = self.vels = self.sampled_opacities = None  # only the cut is read from here on
            return self._kept_samples

    def nbytes(self) -> int:
        """Memory held by the samples (and their kept cut, once made)."""
        arrays = [self.means, self.cov6, self.vels, self.sampled_opacities, *(self._kept_samples or {}).values()]
        arrays = [a.numpy() if isinstance(a, torch.Tensor) else a for a in arrays]
        return sum({id(a): a.nbytes for a in arrays if isinstance(a, np.ndarray)}.values())

    def buffer(self, t: float, keep: np.ndarray, header: dict, velocity: bool) -> bytes:
        """The kept dynamic set at `t`, linearly interpolated between the two samples around it,
        written straight into a splat buffer."""
        kept = self._kept(keep)
        k, w = self._bracket(t)

        def lerp_into(a: torch.Tensor, out: np.ndarray) -> None:
            # torch, not numpy: its float32 -> float16 conversion is vectorised, numpy's is not
            # (0.13 ms for a 20,000-splat buffer against 0.73).
            torch.from_numpy(out).copy_(torch.lerp(a[k], a[k + 1], w))

        buf, rec, vel = new_buffer(header, len(kept["index"]), velocity, kept["scale"])
        lerp_into(kept["means"], rec["position"])
        lerp_into(kept["cov6"], rec["covariance"])
        rgba = kept["rgba"]
        if kept["sampled_opacities"] is not None:
            rgba = rgba.copy()
            opacity = torch.lerp(kept["sampled_opacities"][k], kept["sampled_opacities"][k + 1], w).numpy()
            rgba[:, 3] = np.clip(opacity * 255 + 0.5, 0, 255).astype(np.uint8)
        rec["rgba"] = presence_rgba(rgba, kept["lifespan"], t)
        rec["index"] = kept["index"]
        if vel is not None:
            lerp_into(kept["vels"], vel)
        return bytes(buf)


def presence_rgba(rgba: np.ndarray, lifespan: np.ndarray, t: float) -> np.ndarray:
    """`rgba (N, 4) uint8` with the alpha of Gaussians present for part of the clip
    (`lifespan (N, 2)`: centre, width; width inf for the others) scaled to their presence at
    `t`, as `KinematicsGS.present` does."""
    if not np.isfinite(lifespan[:, 1]).any():
        return rgba
    out = rgba.copy()
    factor = presence(torch.from_numpy(lifespan), t).numpy()
    out[:, 3] = np.round(rgba[:, 3] * factor).astype(np.uint8)
    return out


def decomposed_copy(model, tau: float):
    """A copy of `model` decomposed at `tau` in place (`KinematicsGS.decompose`: a Gaussian that
    changes sides keeps its average place, as a re-decomposition in training keeps it), with its own
    canonical Gaussians and the networks shared. Readers keep whichever snapshot they started
    with, so a τ change never mutates a model in use.

    At the model's own τ the copy keeps the decomposition training made: that is not always K > τ (the
    decompositions' reading of the flow, one-way re-decompositions on video ingests), and re-deciding it
    by K would show another model than the one trained."""
    m = copy.copy(model)
    m.config = copy.copy(model.config)
    if m.decomposed:
        m.params = model.params.detach_clone()
        m.dynamic = model.dynamic.clone()
        if tau != model.config.tau:
            m.decompose(tau, recompute=False, in_place=True)
    return m


def edit_label(op: str, count: int) -> str:
    """What an edit did, as the undo history shows it."""
    some = f"{count:,} splat{'s' if count != 1 else ''}"
    return {
        "delete": f"delete {some}",
        "hide": f"hide {some}",
        "crop": "crop",
        "unhide": f"unhide {some}" if count else "unhide all",
        "clear": "clear all edits",
        "restore": f"restore {some}" if count else "restore deleted",
    }.get(op, op)


class RunView:
    """One run loaded for viewing: the model at each LoD, the live τ and the edit layer.

    Thread-safe: `lock` guards the bookkeeping only (which snapshot, which version); model
    evaluation runs outside it on immutable snapshots, one at a time (`compute`), so 50
    clients scrubbing do not oversubscribe two cores."""

    def __init__(self, run_dir: Path):
        self.run: LoadedRun = load_run(run_dir)
        self.lock = threading.RLock()
        self.compute = threading.Lock()
        self.edits: EditLayer = load_edits(run_dir)
        self.tau = float(self.run.model.config.tau)
        self._models: dict[int, object] = {}
        self._static: dict[tuple, bytes] = {}
        self._keep: dict[tuple, np.ndarray] = {}
        self._nothing_dynamic: dict[tuple, bool] = {}
        self._trajectories: dict[tuple, Trajectories] = {}
        self.use_trajectories = True  # False: always evaluate the deformation field exactly
        self.version = 0  # bumped by τ changes and edits: clients re-request the static set
        self._frames: list[dict] | None = None
        self.frame_rate: float | None = None  # frames a second of the scene's clip, when recorded (set by `frames`)

    @property
    def dt(self) -> float:
        return float(self.run.info.get("dt", 1.0))

    def frames(self) -> list[dict]:
        """The run's scene frames as the viewers need them (index, id, time, split, camera);
        empty when the scene is gone. Loaded once."""
        if self._frames is None:
            from kgs_core.data.formats import load_scene

            try:
                scene = load_scene(self.run.scene_path())
                frames, extras = scene.frames, scene.extras or {}
            except ValueError:
                frames, extras = [], {}
            rate = extras.get("fps", (extras.get("ingest") or {}).get("fps"))
            self.frame_rate = float(rate) if isinstance(rate, (int, float)) and rate > 0 else None
            self._frames = [
                {
                    "index": i,
                    "id": f.id,
                    "time": f.time,
                    "split": f.split,
                    "width": f.camera.width,
                    "height": f.camera.height,
                    "K": f.camera.K.tolist(),
                    "viewmat": f.camera.viewmat.tolist(),
                }
                for i, f in enumerate(frames)
            ]
        return self._frames

    def model(self, lod: int | None):
        """(lod, model snapshot) for the current τ."""
        with self.lock:
            lod = self.run.n_levels if lod is None else int(lod)
            if not 1 <= lod <= self.run.n_levels:
                raise ValueError(f"lod must be in 1..{self.run.n_levels}, got {lod}")
            if lod not in self._models:
                self._models[lod] = decomposed_copy(self.run.level(lod), self.tau)
            return lod, self._models[lod]

    def state(self, lod: int | None):
        """(lod, model, keep mask, version), consistent with each other; the mask is made once
        per version (every buffer request asks for it)."""
        with self.lock:
            lod, m = self.model(lod)
            key = (lod, self.version)
            if key not in self._keep:
                self._keep[key] = mask = self.keep(lod, m)
                mask.flags.writeable = False  # shared by every request of this version
            return lod, m, self._keep[key], self.version

    def nothing_dynamic(self, lod: int, model) -> bool:
        """True when the run has no dynamic set to send at this LoD (a static run, or a decomposition
        that left every Gaussian static); asked on every buffer request, so kept per version."""
        with self.lock:
            key = (lod, self.version)
            if key not in self._nothing_dynamic:
                self._nothing_dynamic[key] = self.run.static_only or (model.decomposed and not bool(model.dynamic.any()))
            return self._nothing_dynamic[key]

    def keep(self, lod: int, model) -> np.ndarray:
        return self.edits.keep_mask(lod, model.params.means.detach().numpy())

    def _dynamic_mask(self, model) -> np.ndarray:
        if self.run.static_only:
            return np.zeros(len(model), dtype=bool)
        return model.dynamic.numpy() if model.decomposed else np.ones(len(model), dtype=bool)

    # ------------------------------------------------------------ buffers

    @torch.no_grad()
    def static_buffer(self, lod: int | None = None) -> bytes:
        lod, m, keep, version = self.state(lod)
        key = (lod, version)
        buf = self._static.get(key)
        if buf is None:
            sel = ~self._dynamic_mask(m) & keep
            with self.compute:
                g = m.at_static()
            idx = torch.from_numpy(np.nonzero(sel)[0])
            buf = pack_buffer(
                {"kind": "static", "lod": lod, "version": version},
                g.means[idx].numpy(),
                g.covars6[idx].double().numpy(),
                rgba_of(g.sh[idx], g.opacities[idx]),
                idx.numpy().astype(np.uint32),
            )
            with self.lock:
                if version == self.version:
                    self._static[key] = buf
        if self.use_trajectories:
            self.trajectories(lod, 0.0)  # start building the cache as soon as someone watches
        return buf

    def sh_buffer(self, lod: int | None = None) -> bytes | None:
        """Every Gaussian's SH coefficients after the DC term, by index within the level (the
        same whatever τ or the edits: they do not change a Gaussian's index); None at degree 0."""
        lod, m = self.model(lod)
        rest = m.params.sh_rest.detach()
        if rest.shape[1] == 0:
            return None
        return pack_sh_buffer({"lod": lod, "degree": m.config.sh_degree}, rest.numpy())

    def trajectories(self, lod: int, exposure: float) -> Trajectories | None:
        """The ready trajectory cache for (lod, exposure), starting its build if needed."""
        with self.lock:
            lod, m = self.model(lod)
            if self.nothing_dynamic(lod, m):
                return None
            key = (lod, self.version, round(float(exposure), 6))
            tr = self._trajectories.get(key)
            if tr is None:
                self._trajectories = {k: v for k, v in self._trajectories.items() if k[1] == self.version}
                tr = self._trajectories[key] = Trajectories(self, m, lod, self.version, key[2])
        return tr if tr.ready.is_set() else None

    def camera_shake(self, t: float, exposure: float):
        """The camera's shake an "as captured" render at `t` shows (the nearest training frame's,
        `learned_blur`), None when sharp or when the run kept none. Static Gaussians get it in
        the client (the static set is sent once); the dynamic set and server renders here."""
        if not exposure > 0:
            return None
        return nearest_camera_motion(learned_blur(self.run.info).get("camera_motion"), float(t))

    @torch.no_grad()
    def dynamic_buffer(self, t: float, exposure: float = 0.0, lod: int | None = None, velocity: bool = True, exact: bool = False) -> bytes:
        """The dynamic set at `t`: interpolated from the trajectory cache when it is ready (and
        `exact` is not asked for), else evaluated exactly."""
        lod, m, keep, version = self.state(lod)
        header = {"kind": "dynamic", "lod": lod, "t": t, "exposure": exposure, "version": version}
        if self.nothing_dynamic(lod, m):
            return pack_buffer(
                header, np.zeros((0, 3)), np.zeros((0, 6)), np.zeros((0, 4)), np.zeros(0), np.zeros((0, 3)) if velocity else None
            )
        shake = self.camera_shake(t, exposure)
        # (The trajectory cache samples the objects' motion alone: the camera's shake changes per frame.)
        tr = None if (exact or shake is not None or not self.use_trajectories) else self.trajectories(lod, exposure)
        if tr is not None and tr.key[1] == version:
            return tr.buffer(float(t), keep, {**header, "interpolated": True}, velocity)
        with self.compute:  # without velocities a sharp frame skips their field samples
            idx_t, g = m.at_dynamic(float(t), exposure, self.dt, velocity=velocity, camera_motion=shake)
        idx, means, covs = idx_t.numpy(), g.means.numpy(), g.covars6.numpy()
        vels = g.velocity.numpy() if g.velocity is not None else None
        rgba = rgba_of(g.sh, g.opacities)
        header["interpolated"] = False
        sel = keep[idx]
        return pack_buffer(header, means[sel], covs[sel], rgba[sel], idx[sel].astype(np.uint32), vels[sel] if velocity else None)

    @torch.no_grad()
    def baked(self, t: float, exposure: float = 0.0, lod: int | None = None, subset: str = "all") -> tuple[Baked, int]:
        """All kept Gaussians at `t` (for server-side renders), optionally only one set."""
        lod, m, keep, _ = self.state(lod)
        with self.compute:
            shake = self.camera_shake(t, exposure)
            g = m.at_static() if self.run.static_only else m.at(float(t), exposure=exposure, dt=self.dt, camera_motion=shake)
        dyn = self._dynamic_mask(m)
        sel = keep & {"all": True, "static": ~dyn, "dynamic": dyn}[subset]
        return baked_from(g, sel, dynamic=dyn), lod

    def object_at(self, index: int, t: float, lod: int | None = None) -> dict:
        """The kept dynamic Gaussians connected at time `t` to dynamic Gaussian `index`."""
        from .selection import REACH, connected_object, largest_sigma

        g, lod = self.baked(t, lod=lod, subset="dynamic")
        where = np.nonzero(g.index == index)[0]
        if not len(where):
            raise ValueError(f"Gaussian {index} is not a kept moving Gaussian of LoD {lod}: the object tool selects moving objects")
        members = connected_object(g.means, largest_sigma(g.covars), int(where[0]))
        return {"indices": g.index[members].tolist(), "lod": lod, "reach": REACH}

    # ------------------------------------------------------------ live decomposition and edits

    def set_tau(self, tau: float) -> dict:
        if not (tau > 0 and np.isfinite(tau)):
            raise ValueError(f"tau must be a positive number, got {tau}")
        with self.lock:
            self.tau = float(tau)
            # (From the run's own models, so that moves in place do not add up over τ changes.)
            self._models = {lod: decomposed_copy(self.run.level(lod), self.tau) for lod in self._models}
            self._invalidate()
        return self.decomposition()

    def decomposition(self, lod: int | None = None) -> dict:
        lod, m, keep, version = self.state(lod)
        counts = decomposition_counts(m, self.run.static_only)
        dyn = self._dynamic_mask(m)
        return {
            "tau": self.tau,
            "lod": lod,
            **counts,
            "kept": int(keep.sum()),
            "dynamic_kept": int((dyn & keep).sum()),
            "static_kept": int((~dyn & keep).sum()),
            "version": version,
            "history": self.edits.history_labels(),
        }

    def histogram(self, lod: int | None = None) -> dict:
        _, m = self.model(lod)
        return K_histogram(m.K.numpy())

    def apply_edit(self, op: str, lod: int | None, indices: list[int] | None = None, crop: dict | None = None) -> dict:
        with self.lock:
            lod, m = self.model(lod)
            n = len(m)
            ids = [int(i) for i in (indices or [])]
            bad = [i for i in ids if not 0 <= i < n]
            if bad:
                raise ValueError(f"indices {bad[:5]} outside 0..{n - 1} for LoD {lod}")
            if op in ("undo", "redo"):  # a new layer: readers keep theirs
                edits = self.edits.step(back=op == "undo")
            else:
                edits = self.edits.changed(edit_label(op, len(ids)))
            e = edits.level(lod)
            if op in ("undo", "redo"):
                pass
            elif op == "delete":
                e.deleted.update(ids)
            elif op == "hide":
                e.hidden.update(ids)
            elif op == "unhide":
                e.hidden.difference_update(ids) if ids else e.hidden.clear()
            elif op == "restore":
                e.deleted.difference_update(ids) if ids else e.deleted.clear()
            elif op == "crop":
                layer = EditLayer.from_dict({"crop": crop}, "crop")
                edits.crop_min, edits.crop_max = layer.crop_min, layer.crop_max
            elif op == "clear":
                edits.levels, edits.crop_min, edits.crop_max = {}, None, None
            else:
                raise ValueError(f"unknown edit op {op!r} (delete, hide, unhide, restore, crop, clear, undo, redo)")
            save_edits(self.run.path, edits)
            self.edits = edits
            self._invalidate()
        return self.decomposition(lod)

    def _invalidate(self) -> None:
        self.version += 1
        self._static.clear()
        self._keep.clear()
        self._nothing_dynamic.clear()
        self._trajectories.clear()
