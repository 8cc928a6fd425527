"""C.F.'s neighbour graph over the dynamic Gaussians, as methods of `KinematicsGS` (a mixin):
each dynamic Gaussian's k nearest dynamic neighbours, built at the first decomposition and carried
through densification, pruning and re-decompositions, and the neighbour mean (the coarse deformation)
as a sparse product."""

from __future__ import annotations

import warnings

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor


class NeighbourGraph:
    """Reads and writes `KinematicsGS`'s `_knn`, `_knn_mean`, `dynamic`, `lifespan`, `params` and
    `config`; `set_params` is where the graph is resized with everything else."""

    def _graph_after_keep(self, keep: Tensor, heirs: Tensor | None) -> Tensor | None:
        if self._knn is None:
            return None
        # Each Gaussian's row in the new dynamic set (-1: not in it), then each removed one's heir's.
        kept_dynamic = keep & self.dynamic
        new_row = _row_numbers(kept_dynamic)
        if heirs is not None:
            inherit = ~keep & (heirs >= 0)
            new_row[inherit] = new_row[heirs[inherit]]
        return self._carried_rows(new_row, kept_dynamic)

    def _carried_rows(self, new_row: Tensor, stays: Tensor) -> Tensor:
        """The graph's rows of the dynamic Gaussians where `stays (N,)`, re-indexed by `new_row
        (N,)` (each Gaussian's row in the new dynamic set, or the one that takes its place; -1:
        none, and the row's own Gaussian takes it)."""
        rows = new_row[self.dynamic][self._knn[stays[self.dynamic]]]
        return torch.where(rows >= 0, rows, new_row[stays & self.dynamic][:, None])

    def _graph_after_add(self, parents: Tensor) -> Tensor | None:
        if self._knn is None:
            return None
        # New dynamic Gaussians follow every old one in the dynamic set, in their order: each
        # takes its parent's row with itself in its parent's place.
        parent_rows = (torch.cumsum(self.dynamic, 0) - 1)[parents[self.dynamic[parents]]]
        own = len(self._knn) + torch.arange(len(parent_rows))
        rows = self._knn[parent_rows]
        return torch.cat([self._knn, torch.where(rows == parent_rows[:, None], own[:, None], rows)])

    def knn_index(self) -> Tensor:
        """`(D, k)` indices into the dynamic subset: each dynamic Gaussian's nearest dynamic
        neighbours (itself included), built at the first decomposition and carried from then on."""
        if self._knn is None:
            self._knn = self._nearest_graph(self.dynamic)
        return self._knn

    def _nearest_graph(self, dynamic: Tensor) -> Tensor:
        """`(D, k)`: the nearest members of `dynamic` to each, by canonical mean now."""
        pts = self.params.means.detach()[dynamic].cpu().numpy()
        k = min(self.config.knn, len(pts))
        if k <= 1:
            return torch.arange(len(pts), device=dynamic.device)[:, None]
        dist, idx = cKDTree(pts).query(pts, k=k)
        if self.config.knn_radius > 0:
            far = dist > self.config.knn_radius * np.median(dist[:, -1])
            idx = np.where(far, np.arange(len(pts))[:, None], idx)  # itself in their place
        return torch.as_tensor(idx, dtype=torch.long, device=dynamic.device).reshape(len(pts), k)

    def _graph_after_redecompose(self, dynamic: Tensor) -> Tensor | None:
        if self._knn is None:
            return None
        carried = self._carried_rows(_row_numbers(dynamic), dynamic & self.dynamic)
        newcomers = (dynamic & ~self.dynamic)[dynamic]
        if not newcomers.any():
            return carried
        rows = self._nearest_graph(dynamic)
        if rows.shape[1] != carried.shape[1]:  # the set grew past k: nothing to carry
            return rows
        rows[~newcomers] = carried
        return rows

    def neighbour_mean(self, x: Tensor) -> Tensor:
        """`(D, C)` rows of `x` (one per dynamic Gaussian) averaged over each one's kNN graph
        row (the coarse deformation), as a sparse matrix product `W x`. Gathering `x[knn]`
        instead is the same forward, but its backward (an accumulating index_put) is serial on
        CPU: 10 ms of a 66 ms panel step against 1.4 ms for this.

        Under `spawned_motion="own"` the spawned Gaussians (bounded lifespan) are left out of
        every row (`_own_motion_rows`): the field is not evaluated for them, so their rows of
        `x` carry nothing."""
        knn = self.knn_index()
        own = self._own_motion_rows()
        if self._knn_mean is None or self._knn_mean[0] is not knn or not _same_mask(self._knn_mean[1], own):
            self._knn_mean = (knn, own, *neighbour_mean_matrices(knn, own))
        return _SparseRowMean.apply(x, self._knn_mean[2], self._knn_mean[3])

    def _own_motion_rows(self) -> Tensor | None:
        """`(D,) bool` over the dynamic set: the Gaussians that move on their own line
        (`spawned_motion="own"`, bounded lifespan), whose field offsets nobody reads; None
        when there are none."""
        if self.config.spawned_motion != "own":
            return None
        own = self.lifespan[self.dynamic, 1].isfinite()
        return own if own.any() else None


def _row_numbers(members: Tensor) -> Tensor:
    """`(N,)`: each Gaussian's row in the subset `members (N,) bool` indexes, -1 outside it."""
    rows = torch.full((len(members),), -1, dtype=torch.long)
    rows[members] = torch.arange(int(members.sum()))
    return rows


def checked_knn(knn, n_dynamic: int) -> Tensor | None:
    """A stored kNN graph, checked against the dynamic set it indexes (a graph from another
    state would index out of range deep inside rendering)."""
    if knn is None:
        return None
    ok = (
        isinstance(knn, Tensor)
        and knn.dtype == torch.long
        and knn.dim() == 2
        and len(knn) == n_dynamic
        and (knn.numel() == 0 or (int(knn.min()) >= 0 and int(knn.max()) < n_dynamic))
    )
    if not ok:
        shape = tuple(knn.shape) if isinstance(knn, Tensor) else type(knn).__name__
        raise ValueError(
            f"model state field 'knn': expected int64 indices of shape ({n_dynamic}, k) into the {n_dynamic} dynamic Gaussians, got {shape}"
        )
    return knn.clone()


def neighbour_mean_matrices(knn: Tensor, drop: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Sparse CSR `W (D, D)` with `W[i, j] = 1/k` for each of row `i`'s `k` neighbours `j`
    (a repeated neighbour counts twice, as in `x[knn].mean(1)`), and its transpose.

    `drop (D,) bool`: those Gaussians are nobody's neighbour; each row averages over the
    neighbours it has left (its own Gaussian alone where none is left)."""
    d, k = knn.shape
    rows = torch.arange(d).repeat_interleave(k)
    cols = knn.reshape(-1)
    weights = torch.full((d * k,), 1.0 / k)
    if drop is not None:
        kept = ~drop[knn]  # (D, k)
        left = kept.sum(1)
        cols = torch.where(left[:, None] > 0, knn, torch.arange(d)[:, None]).reshape(-1)
        weights = torch.where(left[:, None] > 0, kept / left.clamp_min(1)[:, None], 1.0 / k).reshape(-1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
        w = torch.sparse_coo_tensor(torch.stack([rows, cols]), weights.float(), (d, d), check_invariants=True).coalesce()
        return w.to_sparse_csr(), w.t().coalesce().to_sparse_csr()


def _same_mask(a: Tensor | None, b: Tensor | None) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and torch.equal(a, b))


class _SparseRowMean(torch.autograd.Function):
    """`W x` with the gradient `W^T g`, both CSR products (torch's own sparse autograd goes
    through COO and is no faster than the gather)."""

    @staticmethod
    def forward(ctx, x: Tensor, w: Tensor, wt: Tensor) -> Tensor:
        ctx.wt = wt
        return w @ x

    @staticmethod
    def backward(ctx, g: Tensor):
        return ctx.wt @ g.contiguous(), None, None
