"""`kgs-app export`: a run as standard files.

| format  | output                                   | reader                      |
| ------- | ---------------------------------------- | --------------------------- |
| ply-seq | folder of 3DGS `.ply`, one per time      | any 3DGS viewer, plyfile    |
| splat   | folder of antimatter15 `.splat`, one per time | antimatter15/splat      |
| splatv  | one splaTV `.splatv` (fitted motion)     | antimatter15/splaTV         |
| mp4     | video along a camera path                | any player                  |
| glb     | velocity-aligned ellipsoids at one time  | Blender, three.js, trimesh  |

Every export honours the run's edit layer (`RUN/edits.json`), writes to a temporary path renamed
into place, and writes `export.json` (what was exported, and the splatv fit error). A run that
does not move (no dynamic Gaussians, or a static ablation) exports one frame, not N copies.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..data.formats import load_scene
from ..io import atomic_directory, atomic_write_text
from ..job_options import FORMATS  # noqa: E402,F401  (declared with the export's options)
from ..progress import progress_bar
from .bake import ExportSource, bake, open_source, parse_times
from .splatv import splatv_cameras
from .web_frame import ANTIMATTER15, SPLATV, Similarity
from .web_frame import web_frame as frame_for_viewer

SUFFIX = {"splatv": ".splatv", "mp4": ".mp4", "glb": ".glb"}


@dataclass
class ExportResult:
    path: Path
    files: list[Path]
    report: dict = field(default_factory=dict)


def _scene_frames(source: ExportSource, required: bool):
    try:
        return load_scene(source.run.scene_path()).train_frames
    except Exception as exc:
        if required:
            raise ValueError(f"this export needs the run's training scene: {exc}") from None
        return []


def _web_frame(source: ExportSource, frames, fmt: str) -> Similarity:
    """The coordinates that open the file at the first training camera's view (what our viewer
    opens on) in the viewer that reads it: splaTV for .splatv, antimatter15/splat otherwise."""
    cam = frames[0].camera
    means = source.model.params.means.detach().numpy()[source.keep].astype(np.float64)
    return frame_for_viewer(SPLATV if fmt == "splatv" else ANTIMATTER15, cam.viewmat, cam.K, cam.width, means)


def _cameras(source: ExportSource, frames) -> list[dict]:
    cams = splatv_cameras(frames)
    return [source.frame.camera(c) for c in cams] if source.frame is not None else cams


def default_times(source: ExportSource, frames) -> list[float]:
    if frames:
        return sorted({f.time for f in frames})
    n = int(source.run.info.get("frames", 30))
    return np.linspace(0, 1, max(n, 2)).tolist()


def export_run(
    run_dir: str | Path,
    fmt: str,
    out: str | Path | None = None,
    times: str | None = None,
    camera_path: str = "training",
    exposure: float = 0.0,
    lod: int | None = None,
    side_by_side: bool = False,
    fps: float = 24.0,
    overwrite: bool = False,
    progress: bool = True,
    size: int | None = None,
    view: dict | None = None,
    web_frame: bool | None = None,
    keyframes: str | Path | None = None,
) -> ExportResult:
    """The options are `kgs_core.job_options.ExportOptions` (checked there, the command line's
    and the server's alike; a bad one is a ValueError naming it); `keyframes`: an mp4's camera
    path from a JSON file (`camera_path.keyframe_path`) instead of `camera_path`."""
    from pydantic import ValidationError

    from ..job_options import ExportOptions, first_error

    try:
        o = ExportOptions(
            format=fmt,
            times=times,
            camera_path=camera_path,
            view=view,
            exposure=exposure,
            lod=lod,
            side_by_side=side_by_side,
            size=size,
            fps=fps,
            web_frame=web_frame,
        )
    except ValidationError as exc:
        raise ValueError(first_error(exc)) from None
    if keyframes is not None and (fmt != "mp4" or times is not None or side_by_side or camera_path != "training"):
        raise ValueError(
            "keyframes: a video's camera path of its own, with its own times (only with format mp4, "
            "not with times, side_by_side or another camera_path)"
        )
    view = o.view.model_dump() if o.view is not None else None
    source = open_source(run_dir, lod)
    if not source.keep.any():
        raise ValueError("nothing to export: the edit layer removes every Gaussian")
    run_dir = Path(run_dir)
    name = f"{fmt}_lod{source.lod}" + (f"_exp{exposure:g}" if exposure else "")
    out = Path(out) if out else run_dir / "exports" / (name + SUFFIX.get(fmt, ""))
    if fmt in SUFFIX and out.suffix.lower() != SUFFIX[fmt]:
        out = out.with_name(out.name + SUFFIX[fmt])  # `--out scene` writes scene.splatv, as documented
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} already exists (pass --force to replace it)")
    report = {
        "format": fmt,
        "run": str(run_dir),
        "lod": source.lod,
        "exposure": exposure,
        "gaussians": int(source.keep.sum()),
        "edited_out": int((~source.keep).sum()),
        "moves": source.moves,
    }
    if web_frame is None:
        web_frame = fmt in ("splat", "splatv")
    if web_frame:
        frames = _scene_frames(source, required=False)
        if frames:
            source.frame = _web_frame(source, frames, fmt)
            report["web_frame"] = {
                "viewer": (SPLATV if fmt == "splatv" else ANTIMATTER15).name,
                "file_from_run": source.frame.matrix().tolist(),
            }
        else:
            report["note"] = "no training cameras to frame the file for the web viewers: written in run coordinates"

    if fmt in ("ply-seq", "splat"):
        from .ply import write_ply
        from .splat import write_splat

        frames = _scene_frames(source, required=False)
        ts = parse_times(times, default_times(source, frames))
        if not source.moves:
            report["note"] = f"the run does not move: one frame written instead of {len(ts)} identical ones"
            ts = ts[:1]
        writer, ext = (write_ply, ".ply") if fmt == "ply-seq" else (write_splat, ".splat")
        files = []
        with atomic_directory(out, overwrite=overwrite) as tmp:
            for i, t in enumerate(progress_bar(ts, desc=f"export {fmt}", stage="write frames", show=progress)):
                fname = f"frame_{i:05d}{ext}"
                writer(tmp / fname, bake(source, t, exposure))
                files.append(fname)
            report["frames"] = [{"file": f, "time": t} for f, t in zip(files, ts)]
            atomic_write_text(tmp / "export.json", json.dumps(report, indent=1))
            if frames:  # the 3DGS convention: dropped on antimatter15/splat or splaTV, it sets their view
                atomic_write_text(tmp / "cameras.json", json.dumps(_cameras(source, frames), indent=1))
        return ExportResult(out, [out / f for f in files], report)

    if fmt == "splatv":
        from .splatv import fit_splatv, write_splatv

        frames = _scene_frames(source, required=False)
        ts = parse_times(times, default_times(source, frames))
        if len(ts) < 4 and source.moves:
            ts = np.linspace(min(ts), max(ts), 32).tolist() if max(ts) > min(ts) else np.linspace(0, 1, 32).tolist()
        words, fit = fit_splatv(source, ts, exposure, progress)
        write_splatv(out, words, _cameras(source, frames))
        report["fit"] = fit.to_dict()
    elif fmt == "glb":
        from .glb import write_glb

        ts = parse_times(times, [0.5])
        if len(ts) != 1:
            raise ValueError("glb exports one time: give one time")
        report["time"] = ts[0]
        report.update(write_glb(out, bake(source, ts[0], exposure)))
    else:  # mp4
        from .camera_path import keyframe_path, orbit_path, training_path, view_path
        from .video import render_path, write_video

        if keyframes is not None:
            steps = keyframe_path(keyframes)
        elif camera_path == "view":
            steps = view_path(view, parse_times(times, np.linspace(0, 1, 60).tolist()))
        elif camera_path == "training":
            frames = _scene_frames(source, required=True)
            steps = training_path(frames, None if times is None else parse_times(times, []))
        else:  # orbit
            frames = _scene_frames(source, required=True)
            centre = np.median(source.model.params.means.detach().numpy()[source.keep], axis=0)
            steps = orbit_path(frames, centre, parse_times(times, np.linspace(0, 1, 120).tolist()))
        if size is not None:  # the long side in pixels, every camera scaled alike
            steps = [replace(s, camera=s.camera.scaled(size / max(s.camera.width, s.camera.height))) for s in steps]
        images = render_path(source, steps, exposure, side_by_side, progress=progress)
        write_video(out, images, fps, progress)
        report.update(
            {
                "camera_path": "keyframes" if keyframes is not None else camera_path,
                "frames": len(images),
                "fps": fps,
                "times": [s.time for s in steps][:1000],
            }
        )
    atomic_write_text(out.with_name(out.name + ".json"), json.dumps(report, indent=1))
    return ExportResult(out, [out], report)
