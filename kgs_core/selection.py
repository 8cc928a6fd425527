"""Selecting an object: the Gaussians connected to one, for the editor's "object" tool.

A moving object is a cluster of dynamic Gaussians, apart from the others at the moment it is
looked at. `connected_object` grows the cluster from the clicked Gaussian through Gaussians
whose extents touch (centres closer than `REACH` times the sum of their largest standard
deviations), so it follows the object's own shape, bridges its sparse parts (where Gaussians
are large) and stops at empty space.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

REACH = 2.0  # two Gaussians touch when their 2-sigma spheres do
SIZE_CLIP = 99  # percentile the sizes are clipped at: one huge floater must not join everything


def largest_sigma(covars: np.ndarray) -> np.ndarray:
    """The standard deviation along each covariance's longest axis, `(N, 3, 3) -> (N,)`."""
    return np.sqrt(np.maximum(np.linalg.eigvalsh(covars)[:, -1], 0.0))


def connected_object(points: np.ndarray, sizes: np.ndarray, seed: int, reach: float = REACH) -> np.ndarray:
    """Indices into `points (N, 3)` of the component holding `seed`, where two points join when
    their distance is at most `reach * (size_i + size_j)` (`sizes (N,)`, e.g. `largest_sigma`),
    sorted."""
    points = np.asarray(points, dtype=np.float64)
    sizes = np.asarray(sizes, dtype=np.float64)
    if not 0 <= seed < len(points):
        raise ValueError(f"seed {seed} outside 0..{len(points) - 1}")
    if sizes.shape != (len(points),) or not (np.isfinite(points).all() and np.isfinite(sizes).all()):
        raise ValueError("points and sizes must be finite, one size a point")
    sizes = np.minimum(np.maximum(sizes, 0.0), np.percentile(sizes, SIZE_CLIP))
    if len(points) == 1 or sizes.max() <= 0:
        return np.array([seed])
    tree = cKDTree(points)
    near = tree.sparse_distance_matrix(tree, 2 * reach * sizes.max(), output_type="coo_matrix")
    touch = near.data <= reach * (sizes[near.row] + sizes[near.col])
    graph = coo_matrix((np.ones(int(touch.sum())), (near.row[touch], near.col[touch])), shape=near.shape)
    _, labels = connected_components(graph, directed=False)
    return np.nonzero(labels == labels[seed])[0]
