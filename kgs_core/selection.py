"""Selecting an object: the Gaussians connected to one, for the editor's "object" tool.

A moving object is a cluster of dynamic Gaussians, apart from the others at the moment it is
looked at. `connected_object` grows the cluster from the clicked Gaussian through neighbours
closer than `gap` (by default a few times the set's typical nearest-neighbour spacing), so it
follows the object's own shape and stops at empty space.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

GAP_SPACINGS = 4.0  # the gap that separates two objects, in median nearest-neighbour spacings


def typical_spacing(points: np.ndarray) -> float:
    """The median distance from each point to its nearest other point (0 for fewer than two)."""
    if len(points) < 2:
        return 0.0
    d, _ = cKDTree(points).query(points, k=2)
    return float(np.median(d[:, 1]))


def connected_object(points: np.ndarray, seed: int, gap: float | None = None) -> np.ndarray:
    """Indices into `points (N, 3)` of the component holding `seed` when points closer than
    `gap` are joined (default `GAP_SPACINGS` × `typical_spacing`), sorted."""
    points = np.asarray(points, dtype=np.float64)
    if not 0 <= seed < len(points):
        raise ValueError(f"seed {seed} outside 0..{len(points) - 1}")
    if not np.isfinite(points).all():
        raise ValueError("points must be finite")
    gap = GAP_SPACINGS * typical_spacing(points) if gap is None else float(gap)
    if len(points) == 1 or gap <= 0:
        return np.array([seed])
    graph = cKDTree(points).sparse_distance_matrix(cKDTree(points), gap, output_type="coo_matrix")
    _, labels = connected_components(graph, directed=False)
    return np.nonzero(labels == labels[seed])[0]
