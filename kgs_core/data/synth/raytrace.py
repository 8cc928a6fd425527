"""A small analytic ray tracer (numpy) for the synthetic scenes.

It is deliberately independent of the Gaussian rasteriser: ground truth must not share code
with what it tests. Shapes live in their own object frame; `Object.pose(t)` places them in the
world (rigid), and a shape may deform over time (ellipsoid radii, sheet height field).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

Pose = Callable[[float], np.ndarray]  # t -> (4, 4) object-to-world


# ---------------------------------------------------------------- textures


def value_noise(uv: np.ndarray, seed: int, cells: int) -> np.ndarray:
    """Smooth random values in [0, 1] on a `cells x cells` lattice, bilinear, periodic."""
    rng = np.random.default_rng(seed)
    lattice = rng.random((cells, cells, 3))
    x = (uv[..., 0] % 1.0) * cells
    y = (uv[..., 1] % 1.0) * cells
    x0, y0 = np.floor(x).astype(int) % cells, np.floor(y).astype(int) % cells
    x1, y1 = (x0 + 1) % cells, (y0 + 1) % cells
    fx, fy = (x - np.floor(x))[..., None], (y - np.floor(y))[..., None]
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    top = lattice[y0, x0] * (1 - fx) + lattice[y0, x1] * fx
    bot = lattice[y1, x0] * (1 - fx) + lattice[y1, x1] * fx
    return top * (1 - fy) + bot * fy


@dataclass
class Texture:
    """Colourful multi-octave noise with a checker overlay: corners and blobs for SIFT."""

    seed: int
    base: tuple[float, float, float] = (0.6, 0.6, 0.6)
    checker: int = 8
    contrast: float = 0.6

    def __call__(self, uv: np.ndarray, face: np.ndarray | None = None) -> np.ndarray:
        if face is not None:
            uv = uv + face[..., None] * 0.37  # different look per face
        n = 0.5 * value_noise(uv, self.seed, 6) + 0.3 * value_noise(uv, self.seed + 1, 17) + 0.2 * value_noise(uv, self.seed + 2, 41)
        chk = ((np.floor(uv[..., 0] * self.checker) + np.floor(uv[..., 1] * self.checker)) % 2)[..., None]
        col = np.asarray(self.base) * (1 - self.contrast) + self.contrast * n
        return np.clip(col * (0.75 + 0.25 * chk), 0, 1)


@dataclass
class DieTexture:
    """White faces with black pips (1-6), faces indexed 0..5."""

    pip_radius: float = 0.09

    def __call__(self, uv: np.ndarray, face: np.ndarray) -> np.ndarray:
        layouts = {
            1: [(0.5, 0.5)],
            2: [(0.25, 0.25), (0.75, 0.75)],
            3: [(0.25, 0.25), (0.5, 0.5), (0.75, 0.75)],
            4: [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)],
            5: [(0.25, 0.25), (0.75, 0.25), (0.5, 0.5), (0.25, 0.75), (0.75, 0.75)],
            6: [(0.25, 0.2), (0.25, 0.5), (0.25, 0.8), (0.75, 0.2), (0.75, 0.5), (0.75, 0.8)],
        }
        col = np.empty(uv.shape[:-1] + (3,))
        col[:] = (0.95, 0.93, 0.88)
        border = np.minimum(uv, 1 - uv).min(axis=-1) < 0.04
        col[border] = (0.7, 0.15, 0.1)
        for f in range(6):
            sel = face == f
            if not sel.any():
                continue
            for cx, cy in layouts[f + 1]:
                d = np.hypot(uv[..., 0] - cx, uv[..., 1] - cy)
                col[sel & (d < self.pip_radius)] = (0.05, 0.05, 0.1)
        return col


# ---------------------------------------------------------------- shapes


@dataclass
class Hit:
    s: np.ndarray  # (R,) ray parameter, inf where missed
    local: np.ndarray  # (R, 3) hit point in the shape's rest frame (before deformation)
    normal: np.ndarray  # (R, 3) object-frame normal
    uv: np.ndarray  # (R, 2)
    face: np.ndarray  # (R,) int


def _empty(n: int) -> Hit:
    return Hit(np.full(n, np.inf), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 2)), np.zeros(n, dtype=int))


@dataclass
class Plane:
    """Rectangle `|x| <= w/2, |y| <= h/2` at `z = 0`, two-sided."""

    w: float
    h: float

    def intersect(self, o, d, t):
        hit = _empty(len(o))
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -o[:, 2] / d[:, 2]
        p = o + s[:, None] * d
        ok = (s > 1e-6) & (np.abs(p[:, 0]) <= self.w / 2) & (np.abs(p[:, 1]) <= self.h / 2)
        hit.s[ok] = s[ok]
        hit.local[ok] = p[ok]
        hit.normal[ok] = (0, 0, 1)
        hit.uv[ok] = np.stack([p[ok, 0] / self.w + 0.5, p[ok, 1] / self.h + 0.5], -1)
        return hit

    def deform(self, local, t):
        return local


@dataclass
class Box:
    half: tuple[float, float, float]

    def intersect(self, o, d, t):
        hit = _empty(len(o))
        h = np.asarray(self.half)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            t0, t1 = (-h - o) * inv, (h - o) * inv
        tmin, tmax = np.minimum(t0, t1).max(axis=1), np.maximum(t0, t1).min(axis=1)
        s = np.where(tmin > 1e-6, tmin, tmax)
        ok = (tmax >= tmin) & (s > 1e-6)
        p = o[ok] + s[ok, None] * d[ok]
        q = p / h
        axis = np.abs(q).argmax(axis=1)
        sign = np.sign(q[np.arange(len(q)), axis])
        face = axis * 2 + (sign < 0)
        normal = np.zeros_like(p)
        normal[np.arange(len(p)), axis] = sign
        others = np.array([[1, 2], [0, 2], [0, 1]])[axis]
        uv = np.stack([q[np.arange(len(q)), others[:, 0]], q[np.arange(len(q)), others[:, 1]]], -1) * 0.5 + 0.5
        hit.s[ok], hit.local[ok], hit.normal[ok], hit.uv[ok], hit.face[ok] = s[ok], p, normal, uv, face
        return hit

    def deform(self, local, t):
        return local


@dataclass
class Ellipsoid:
    """Radii may change with time (squash and stretch). `local` is the unit-sphere point."""

    radii: Callable[[float], np.ndarray]

    def intersect(self, o, d, t):
        hit = _empty(len(o))
        r = np.asarray(self.radii(t), dtype=float)
        o2, d2 = o / r, d / r
        a = (d2 * d2).sum(1)
        b = 2 * (o2 * d2).sum(1)
        c = (o2 * o2).sum(1) - 1
        disc = b * b - 4 * a * c
        ok = disc >= 0
        sq = np.sqrt(np.where(ok, disc, 0))
        s0, s1 = (-b - sq) / (2 * a), (-b + sq) / (2 * a)
        s = np.where(s0 > 1e-6, s0, s1)
        ok &= s > 1e-6
        unit = o2[ok] + s[ok, None] * d2[ok]
        n = unit / r
        hit.s[ok] = s[ok]
        hit.local[ok] = unit
        hit.normal[ok] = n / np.linalg.norm(n, axis=1, keepdims=True)
        u = np.arctan2(unit[:, 1], unit[:, 0]) / (2 * np.pi) + 0.5
        v = np.arccos(np.clip(unit[:, 2], -1, 1)) / np.pi
        hit.uv[ok] = np.stack([u, v], -1)
        return hit

    def deform(self, local, t):
        return local * np.asarray(self.radii(t))


@dataclass
class Sheet:
    """Height field `z = height(x, y, t)` over `|x| <= w/2, |y| <= h/2`, |height| <= amp.
    `local` is the rest point `(x, y, 0)`; found by marching then bisection."""

    w: float
    h: float
    amp: float
    height: Callable[[np.ndarray, np.ndarray, float], np.ndarray]
    steps: int = 24  # march steps before bisection; the wave spans < 2 periods of the sheet

    def intersect(self, o, d, t):
        hit = _empty(len(o))
        with np.errstate(divide="ignore", invalid="ignore"):
            sa, sb = (-self.amp - o[:, 2]) / d[:, 2], (self.amp - o[:, 2]) / d[:, 2]
        lo, hi = np.maximum(np.minimum(sa, sb), 1e-6), np.maximum(sa, sb)
        valid = np.isfinite(lo) & np.isfinite(hi) & (hi > lo)
        # March only the rays whose path through the slab passes over the sheet's rectangle.
        with np.errstate(invalid="ignore"):
            ends = [o + np.where(valid, s, 0.0)[:, None] * d for s in (lo, hi)]
        for axis, half in ((0, self.w / 2), (1, self.h / 2)):
            valid &= np.maximum(ends[0][:, axis], ends[1][:, axis]) >= -half
            valid &= np.minimum(ends[0][:, axis], ends[1][:, axis]) <= half
        rays = np.nonzero(valid)[0]
        o, d, lo, hi = o[rays], d[rays], lo[rays], hi[rays]
        valid = np.ones(len(rays), bool)

        def f(s):
            p = o + s[:, None] * d
            return p[:, 2] - self.height(p[:, 0], p[:, 1], t), p

        found = np.zeros(len(o), bool)
        a = lo.copy()
        b = hi.copy()
        fa, _ = f(lo)
        for k in range(1, self.steps + 1):
            sk = lo + (hi - lo) * k / self.steps
            fk, _ = f(sk)
            cross = valid & ~found & (np.sign(fk) != np.sign(fa))
            b[cross] = sk[cross]
            found |= cross
            a = np.where(found, a, sk)
            fa = np.where(found, fa, fk)
        for _ in range(14):  # ~1e-5 of the slab thickness
            m = 0.5 * (a + b)
            fm, _ = f(m)
            left = np.sign(fm) == np.sign(fa)
            a, fa = np.where(left, m, a), np.where(left, fm, fa)
            b = np.where(left, b, m)
        s = 0.5 * (a + b)
        _, p = f(s)
        ok = found & (np.abs(p[:, 0]) <= self.w / 2) & (np.abs(p[:, 1]) <= self.h / 2)
        e = 1e-4
        dzdx = (self.height(p[:, 0] + e, p[:, 1], t) - self.height(p[:, 0] - e, p[:, 1], t)) / (2 * e)
        dzdy = (self.height(p[:, 0], p[:, 1] + e, t) - self.height(p[:, 0], p[:, 1] - e, t)) / (2 * e)
        n = np.stack([-dzdx, -dzdy, np.ones_like(dzdx)], -1)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        at = rays[ok]
        hit.s[at] = s[ok]
        hit.local[at] = np.stack([p[ok, 0], p[ok, 1], np.zeros(ok.sum())], -1)
        hit.normal[at] = n[ok]
        hit.uv[at] = np.stack([p[ok, 0] / self.w + 0.5, p[ok, 1] / self.h + 0.5], -1)
        return hit

    def deform(self, local, t):
        out = local.copy()
        out[:, 2] = self.height(local[:, 0], local[:, 1], t)
        return out


@dataclass
class Object:
    name: str
    shape: object
    texture: Callable
    pose: Pose
    dynamic: bool = False

    def world_point(self, local: np.ndarray, t: float) -> np.ndarray:
        """Where the material point `local` is at time `t` (for ground-truth motion)."""
        p = self.shape.deform(local, t)
        T = self.pose(t)
        return p @ T[:3, :3].T + T[:3, 3]


@dataclass
class RayResult:
    color: np.ndarray  # (R, 3)
    obj: np.ndarray  # (R,) index of the hit object, -1 for background
    local: np.ndarray  # (R, 3) material point of the hit
    depth: np.ndarray  # (R,) ray parameter (inf on miss)


@dataclass
class World:
    objects: list[Object]
    background: tuple[float, float, float] = (0.55, 0.65, 0.8)
    light: np.ndarray = field(default_factory=lambda: np.array([0.4, -0.3, 0.85]) / np.linalg.norm([0.4, -0.3, 0.85]))

    def trace(self, origins: np.ndarray, dirs: np.ndarray, t: float) -> RayResult:
        n = len(origins)
        best = np.full(n, np.inf)
        obj = np.full(n, -1)
        local, normal = np.zeros((n, 3)), np.zeros((n, 3))
        uv, face = np.zeros((n, 2)), np.zeros(n, dtype=int)
        for k, ob in enumerate(self.objects):
            T = ob.pose(t)
            R, c = T[:3, :3], T[:3, 3]
            hit = ob.shape.intersect((origins - c) @ R, dirs @ R, t)  # rays in the object frame
            closer = hit.s < best
            best[closer], obj[closer] = hit.s[closer], k
            local[closer], uv[closer], face[closer] = hit.local[closer], hit.uv[closer], hit.face[closer]
            normal[closer] = hit.normal[closer] @ R.T
        # Shade only the visible surface: one texture evaluation per pixel.
        color = np.empty((n, 3))
        color[:] = self.background
        for k, ob in enumerate(self.objects):
            sel = obj == k
            if sel.any():
                # Two-sided diffuse with a strong ambient term: appearance stays close to albedo.
                shade = 0.7 + 0.3 * np.abs(normal[sel] @ self.light)
                color[sel] = ob.texture(uv[sel], face[sel]) * shade[:, None]
        return RayResult(color, obj, local, best)
