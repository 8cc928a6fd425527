"""Velocity-aligned ellipsoids at one time as a binary glTF (`.glb`, via trimesh): one mesh for
the static set, one for the dynamic set, coloured differently, so any 3D tool shows the
decomposition and how the kinematic covariance stretched the moving Gaussians."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import atomic_write_bytes
from .bake import Baked

STATIC_RGBA = (110, 140, 200, 255)
DYNAMIC_RGBA = (255, 140, 0, 255)


def ellipsoid_mesh(g: Baked, select: np.ndarray, sigma: float, rgba: tuple, subdivisions: int = 1):
    import trimesh

    unit = trimesh.creation.icosphere(subdivisions=subdivisions)
    v0, f0 = np.asarray(unit.vertices), np.asarray(unit.faces)
    cov = g.covars[select]
    evals, evecs = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, 1, 2)))
    A = evecs * (sigma * np.sqrt(np.maximum(evals, 0.0)))[:, None, :]  # maps the unit sphere to the ellipsoid
    verts = g.means[select][:, None, :] + np.einsum("nij,vj->nvi", A, v0)
    faces = f0[None] + (np.arange(len(cov)) * len(v0))[:, None, None]
    mesh = trimesh.Trimesh(vertices=verts.reshape(-1, 3), faces=faces.reshape(-1, 3), process=False)
    mesh.visual.vertex_colors = np.tile(np.asarray(rgba, dtype=np.uint8), (len(mesh.vertices), 1))
    return mesh


def glb_bytes(g: Baked, sigma: float = 2.0, max_ellipsoids: int = 10000) -> tuple[bytes, dict]:
    """The `.glb` and a summary. Above `max_ellipsoids`, the most opaque ones are kept (a dense
    cloud of ellipsoids hides itself anyway)."""
    import trimesh

    keep = np.ones(len(g), dtype=bool)
    if len(g) > max_ellipsoids:
        keep[:] = False
        keep[np.argsort(-g.opacities, kind="stable")[:max_ellipsoids]] = True
    scene = trimesh.Scene()
    counts = {}
    for name, sel, rgba in (("static", keep & ~g.dynamic, STATIC_RGBA), ("dynamic", keep & g.dynamic, DYNAMIC_RGBA)):
        counts[name] = int(sel.sum())
        if sel.any():
            scene.add_geometry(ellipsoid_mesh(g, sel, sigma, rgba), geom_name=name, node_name=name)
    if not scene.geometry:
        raise ValueError("glb: no Gaussians to export (all removed by the edit layer?)")
    data = scene.export(file_type="glb")
    return data, {"ellipsoids": counts, "sigma": sigma, "left_out_low_opacity": int((~keep).sum())}


def write_glb(path: str | Path, g: Baked, sigma: float = 2.0, max_ellipsoids: int = 10000) -> dict:
    data, info = glb_bytes(g, sigma, max_ellipsoids)
    atomic_write_bytes(path, data)
    return info
