"""The occupancy count behind docs/rasterizer.md ("Measured and not kept") against independent counts."""

import torch

from kgs_app.bench.occupancy import occupancy
from kgs_core.render import cpu_backend, rasterize
from kgs_core.render.random_scene import random_scene
from kgs_core.render.types import ALPHA_MAX, ALPHA_MIN, TILE


def test_occupancy_matches_tile_lists_and_a_dense_count():
    res = 64
    sc = random_scene(400, res, res, seed=3, anisotropy=6.0)
    with torch.no_grad():
        proj = cpu_backend.project(
            sc.means, cpu_backend.packed_covariance(sc.quats, sc.scales), sc.opacities, sc.viewmat, sc.K, res, res, 0.01, 1e10, 0.3, False
        )
        out = rasterize(
            sc.means, sc.opacities, sc.viewmat, sc.K, res, res, quats=sc.quats, scales=sc.scales, colors=sc.colors, backend="cpu"
        )
    occ = occupancy(proj.means2d, proj.conics, proj.opacities, proj.bbox, chunk=97)

    # Pairs: the C++ binning's bounding-box tile lists.
    assert occ.pairs == int(out.info["tile_offsets"][-1])
    # Rows: each pair's box clipped to its tile, counted tile by tile.
    rows = 0
    for x0, y0, x1, y1 in proj.bbox[proj.radii > 0].tolist():
        for ty in range(y0 // TILE, (y1 - 1) // TILE + 1):
            rows += (min(y1, ty * TILE + TILE) - max(y0, ty * TILE)) * ((x1 - 1) // TILE - x0 // TILE + 1)
    assert occ.rows == rows
    # Lanes: (pixel, Gaussian) pairs passing the alpha test inside the box, counted densely.
    ys, xs = torch.meshgrid(torch.arange(res) + 0.5, torch.arange(res) + 0.5, indexing="ij")
    vis = proj.radii > 0
    m, c, o, b = proj.means2d[vis].double(), proj.conics[vis].double(), proj.opacities[vis].double(), proj.bbox[vis]
    dx, dy = xs[None] - m[:, 0, None, None], ys[None] - m[:, 1, None, None]
    power = -0.5 * (c[:, 0, None, None] * dx**2 + 2 * c[:, 1, None, None] * dx * dy + c[:, 2, None, None] * dy**2)
    alpha = (o[:, None, None] * power.exp()).clamp(max=ALPHA_MAX)
    inside = (
        (xs[None] >= b[:, 0, None, None])
        & (xs[None] < b[:, 2, None, None])
        & (ys[None] >= b[:, 1, None, None])
        & (ys[None] < b[:, 3, None, None])
    )
    passed = (power <= 0) & (alpha >= ALPHA_MIN) & inside
    assert occ.lanes_drawn == int(passed.sum())
    # Rows and pairs that draw: every drawn lane lies in one, and some of each are empty here.
    assert 0 < occ.pairs_drawn < occ.pairs and 0 < occ.rows_drawn < occ.rows
    assert occ.rows_drawn <= occ.lanes_drawn <= TILE * occ.rows_drawn
