"""What the fast preset's fitting (`fitting.fit_to_scene`) measures of a scene from its cameras
and SfM points: pixels per scene unit, and the streak the camera's own motion draws."""

from __future__ import annotations

import numpy as np


def camera_blur_px(scene, exposure: float | None = None) -> float | None:
    """The median length in pixels of the streak the training camera's own motion draws during
    the exposure: the SfM points' image motion between each frame's neighbours in time (half of
    it per frame interval, median over points, then over frames) times the exposure. None
    without points or fewer than three training frames."""
    frames = sorted(scene.train_frames, key=lambda f: f.time)
    if len(scene.points) < 10 or len(frames) < 3:
        return None
    pts = scene.points[np.random.default_rng(0).choice(len(scene.points), min(2000, len(scene.points)), replace=False)]

    def project(camera):
        c = pts @ camera.viewmat[:3, :3].T + camera.viewmat[:3, 3]
        uv = c @ camera.K.T
        return uv[:, :2] / np.maximum(c[:, 2:3], 1e-6), c[:, 2] > 1e-6

    per_frame = []
    for a, b in zip(frames[:-2], frames[2:]):
        (ua, fa), (ub, fb) = project(a.camera), project(b.camera)
        seen = fa & fb
        if seen.any():
            per_frame.append(0.5 * float(np.median(np.linalg.norm(ub[seen] - ua[seen], axis=1))))
    if not per_frame:
        return None
    return float(np.median(per_frame)) * (scene.exposure if exposure is None else exposure)


def scene_pixels_per_unit(scene) -> float | None:
    """Median focal length over median depth of the SfM points, over the training cameras:
    how many pixels one normalised scene unit spans at the scene's typical depth. None without
    points in front of the cameras."""
    frames = scene.train_frames[:: max(1, len(scene.train_frames) // 16)]
    if len(scene.points) < 10 or not frames:
        return None
    ratios = []
    for f in frames:
        z = scene.points @ f.camera.viewmat[2, :3] + f.camera.viewmat[2, 3]
        z = z[z > 1e-6]
        if len(z):
            ratios.append(f.camera.K[0, 0] / float(np.median(z)))
    return float(np.median(ratios)) if ratios else None
