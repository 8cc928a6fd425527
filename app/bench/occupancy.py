"""How much of the tile kernels' work draws a pixel, on the rasteriser benchmark's scene.

The kernels walk every (tile, Gaussian) pair of the bounding-box tile lists, every row of
the pair's box clipped to the tile, as one 16-lane vector per row. This counts, exactly (in
float64, with the kernels' per-lane test `power <= 0 and alpha >= 1/255`), how many of
those pairs and rows reach a pixel centre at all and how many lanes of a row do. Numbers
and what they meant for the kernels: docs/rasterizer.md, "Measured and not kept".

    python -m kgs_app.bench.occupancy [--n 50000] [--res 256] [--seed 0]
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass

import numpy as np
import torch

from kgs_core.render import cpu_backend
from kgs_core.render.random_scene import random_scene
from kgs_core.render.types import ALPHA_MAX, ALPHA_MIN, TILE


@dataclass
class Occupancy:
    pairs: int  # (tile, Gaussian) pairs of the bounding-box lists
    pairs_drawn: int  # pairs whose Gaussian reaches some pixel centre of the tile
    rows: int  # rows of the pairs' boxes clipped to their tiles
    rows_drawn: int  # of those, rows with a pixel that passes
    lanes_drawn: int  # (pixel, Gaussian) pairs that pass: the Gaussians per pixel, summed

    @property
    def lanes_per_drawn_row(self) -> float:
        return self.lanes_drawn / max(self.rows_drawn, 1)


def occupancy(means2d, conics, opacities, bbox, chunk: int = 20_000) -> Occupancy:
    """Counts over the visible Gaussians (bbox with x0 < x1): means2d (N, 2), conics (N, 3),
    effective opacities (N,), bbox (N, 4) int pixel boxes (x0, y0, x1, y1), ends exclusive."""
    m, c, o, b = (np.asarray(t, dtype=np.float64) for t in (means2d, conics, opacities, bbox))
    b = b.astype(np.int64)
    vis = (b[:, 2] > b[:, 0]) & (b[:, 3] > b[:, 1])
    m, c, o, b = m[vis], c[vis], o[vis], b[vis]
    t0, t1 = b[:, :2] // TILE, (b[:, 2:] - 1) // TILE + 1  # tile rectangles, ends exclusive
    nx, ny = t1[:, 0] - t0[:, 0], t1[:, 1] - t0[:, 1]
    counts = nx * ny
    g = np.repeat(np.arange(len(b)), counts)
    k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    tx, ty = t0[g, 0] + k % nx[g], t0[g, 1] + k // nx[g]
    total = Occupancy(len(g), 0, 0, 0, 0)
    lane = np.arange(TILE)
    for s in range(0, len(g), chunk):
        gi, px0, py0 = g[s : s + chunk], tx[s : s + chunk] * TILE, ty[s : s + chunk] * TILE
        xs = px0[:, None] + lane  # (P, 16) pixel columns of the tile
        ys = py0[:, None] + lane
        in_x = (xs >= b[gi, 0, None]) & (xs < b[gi, 2, None])
        in_y = (ys >= b[gi, 1, None]) & (ys < b[gi, 3, None])
        dx = xs + 0.5 - m[gi, 0, None]
        dy = ys + 0.5 - m[gi, 1, None]
        a, bb, cc = (c[gi, j, None, None] for j in range(3))
        power = -0.5 * (a * dx[:, None, :] ** 2 + 2 * bb * dx[:, None, :] * dy[:, :, None] + cc * dy[:, :, None] ** 2)
        alpha = np.minimum(ALPHA_MAX, o[gi, None, None] * np.exp(power))
        ok = (power <= 0) & (alpha >= ALPHA_MIN) & in_x[:, None, :] & in_y[:, :, None]  # (P, row, lane)
        total.rows += int(in_y.sum())
        total.rows_drawn += int(ok.any(2).sum())
        total.pairs_drawn += int(ok.any((1, 2)).sum())
        total.lanes_drawn += int(ok.sum())
    return total


def scene_occupancy(n: int, res: int, seed: int = 0) -> Occupancy:
    """The counts for `kgs-app bench raster`'s random scene of n Gaussians at res²."""
    sc = random_scene(n, res, res, seed=seed)
    with torch.no_grad():  # the projection rasterize() runs (its defaults: near, far, eps2d)
        cov6 = cpu_backend.packed_covariance(sc.quats, sc.scales)
        proj = cpu_backend.project(sc.means, cov6, sc.opacities, sc.viewmat, sc.K, res, res, 0.01, 1e10, 0.3, False)
    return occupancy(proj.means2d, proj.conics, proj.opacities, proj.bbox)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=50_000)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.n < 1 or args.res < 1:
        ap.error(f"--n and --res must be positive, got --n {args.n} --res {args.res}")
    occ = scene_occupancy(args.n, args.res, args.seed)
    print(f"N={args.n:,} at {args.res}²: {asdict(occ)}")
    print(
        f"pairs that draw {occ.pairs_drawn / occ.pairs:.1%}, rows per pair {occ.rows / occ.pairs:.2f}, "
        f"rows that draw {occ.rows_drawn / occ.rows:.1%}, lanes per drawn row {occ.lanes_per_drawn_row:.2f} of {TILE}"
    )


if __name__ == "__main__":
    main()
