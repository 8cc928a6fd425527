"""Framing an export for the web viewers that open it with no camera of their own.

antimatter15/splat and splaTV start at a fixed view matrix (their `defaultViewMatrix`) whatever
the file holds; splaTV's stays there until a key is pressed, antimatter15's sways about it. A
scene in our coordinates is then small, oblique or behind that camera. `web_frame` finds the
similarity `x_file = scale * R @ x + t` that puts our opening view (the first training camera,
as our viewer opens) at the viewer's default camera, backed off along its axis where the
viewer's field of view is narrower, and scaled so the content lies at the depth the viewer's
own motion is sized for. The exporter applies it to every baked Gaussian and to cameras.json,
and records it in export.json, so the original coordinates are one inverse away.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .bake import Baked


@dataclass(frozen=True)
class WebViewer:
    name: str
    view: tuple[float, ...]  # its default view matrix, column-major world-to-camera (OpenCV axes)
    fx: float | None  # the focal length it draws with, in window pixels (None: the file's first camera's)
    content_depth: float  # the depth its default motion and near plane are sized for


# Copied from each viewer's `defaultViewMatrix`; antimatter15 draws with its own first camera's focal.
ANTIMATTER15 = WebViewer(
    "antimatter15/splat", (0.47, 0.04, 0.88, 0, -0.11, 0.99, 0.02, 0, -0.88, -0.11, 0.47, 0, 0.07, 0.03, 6.55, 1), 1159.5880733038064, 6.55
)
SPLATV = WebViewer("splaTV", (0.99, 0.01, -0.14, 0, 0.02, 0.99, 0.12, 0, 0.14, -0.12, 0.98, 0, -0.09, -0.26, 0.2, 1), None, 2.0)
REFERENCE_WIDTH = 1280  # the window width the field of view is matched at (splaTV's cameras are sized for it)


def viewer_matrix(viewer: WebViewer) -> np.ndarray:
    """The viewer's default world-to-camera as a row-major 4x4, its rotation made orthonormal
    (the copied matrices are rounded to two decimals)."""
    m = np.asarray(viewer.view, dtype=np.float64).reshape(4, 4).T
    u, _, vt = np.linalg.svd(m[:3, :3])
    m[:3, :3] = u @ vt
    return m


@dataclass(frozen=True)
class Similarity:
    """`x' = scale * R @ x + t` (R a rotation, scale > 0)."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.scale * self.R
        m[:3, 3] = self.t
        return m

    def apply(self, g: Baked) -> Baked:
        """The Gaussians `g` in the new coordinates: centres, covariances (scale²), velocities
        and exposure sweeps (scale), and the degree-1 SH band (a vector under rotation)."""
        s, R = self.scale, self.R
        sh = g.sh.copy()
        if sh.shape[1] > 4:
            raise ValueError(
                "framing for a web viewer rotates the view-dependent colour: SH degree 2 and 3 "
                "are not supported (export without the web framing)"
            )
        if sh.shape[1] == 4:  # basis (-y, z, -x): the coefficients are the vector (-c3, -c1, c2)
            a = np.stack([-sh[:, 3], -sh[:, 1], sh[:, 2]], 1)  # (N, xyz, rgb)
            a = np.einsum("ij,njc->nic", R, a)
            sh[:, 1], sh[:, 2], sh[:, 3] = -a[:, 1], a[:, 2], -a[:, 0]
        return Baked(
            means=(s * g.means.astype(np.float64) @ R.T + self.t).astype(np.float32),
            covars=s * s * np.einsum("ij,njk,lk->nil", R, g.covars, R),
            opacities=g.opacities,
            sh=sh,
            dynamic=g.dynamic,
            velocity=(s * g.velocity.astype(np.float64) @ R.T).astype(np.float32),
            index=g.index,
            sweep=None if g.sweep is None else (s * g.sweep.astype(np.float64) @ R.T).astype(np.float32),
        )

    def camera(self, cam: dict) -> dict:
        """A camera in the 3DGS cameras.json form (centre, camera-to-world rotation), moved along."""
        c = self.scale * self.R @ np.asarray(cam["position"], np.float64) + self.t
        rot = self.R @ np.asarray(cam["rotation"], np.float64)
        return {**cam, "position": c.tolist(), "rotation": rot.tolist()}


def opening_camera(
    viewmat: np.ndarray, K: np.ndarray, width: int, means: np.ndarray, viewer_fx: float, viewer_width: int = REFERENCE_WIDTH
) -> tuple[np.ndarray, float]:
    """(world-to-camera, content depth): the training camera `viewmat`, moved back along its
    axis so that a viewer drawing with focal `viewer_fx` in a `viewer_width` window sees the
    content (the median depth of `means` in front) as wide as the training frame showed it."""
    vm = np.array(viewmat, dtype=np.float64)
    z = means @ vm[2, :3] + vm[2, 3]
    z = z[z > 1e-6]
    depth = float(np.median(z)) if len(z) else 1.0
    ratio = (K[0, 0] / width) / (viewer_fx / viewer_width)  # < 1: the viewer's view is narrower
    back = depth * max(0.0, 1 / ratio - 1)
    vm[2, 3] += back
    return vm, depth + back


def web_frame(viewer: WebViewer, viewmat: np.ndarray, K: np.ndarray, width: int, means: np.ndarray) -> Similarity:
    """The similarity that shows `means`, seen from the training camera `viewmat` (intrinsics
    `K`, `width` pixels), at `viewer`'s default view. A viewer that draws with the file's own
    camera (splaTV) gets that camera with the training field of view, so nothing is backed off."""
    fx = viewer.fx if viewer.fx is not None else K[0, 0] * REFERENCE_WIDTH / width
    W, depth = opening_camera(viewmat, K, width, means, fx)
    V = viewer_matrix(viewer)
    scale = viewer.content_depth / max(depth, 1e-9)
    # Camera coordinates agree up to the scale: V_R x' + V_t = scale (W_R x + W_t).
    R = V[:3, :3].T @ W[:3, :3]
    t = V[:3, :3].T @ (scale * W[:3, 3] - V[:3, 3])
    return Similarity(scale, R, t)
