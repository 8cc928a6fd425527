"""The named synthetic scenes: a textured room (world z up, floor at z = 0) plus moving things.

| name | what moves | why it is here |
|---|---|---|
| `die` | a die tumbling along the floor | rigid motion, rotation + translation |
| `bounce` | an elastic ball, squash and stretch, velocity reversal inside one frame | stiff dynamics |
| `top` | a fast spinning, precessing top | rotational blur, velocity varies across the object |
| `sheet` | a hanging sheet with a travelling wave | non-rigid deformation |
| `cross` | a ball and a box crossing at different depths | occlusion, large displacement |
| `swing` | a pendulum ball swinging across the view, two periods | fast motion of a small object |
| `spin` | a toy spinning three turns about its own axis while it drifts across a table | an object that turns fast while it moves |
| `panel` | a large textured panel swinging in the image plane about its top edge | object motion blur that a field can follow |
| `fastpanel`, `smallpanel` | the panel swinging twice as far; then a third its size | twice the blur; a small object's blur |
| `room` | nothing | static control |
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch

from ...render.camera import look_at as render_look_at
from .raytrace import Box, DieTexture, Ellipsoid, Object, Plane, Sheet, Texture, World


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def rigid(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def static(R: np.ndarray, t) -> Callable[[float], np.ndarray]:
    T = rigid(R, t)
    return lambda _t: T


# Object frame (x, y, z) -> world (x, z, -y): a plane standing upright, facing -y.
UPRIGHT = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])


def room(seed: int) -> list[Object]:
    return [
        Object("floor", Plane(8, 8), Texture(seed + 10, (0.55, 0.45, 0.35), checker=16), static(np.eye(3), (0, 0, 0))),
        Object("back wall", Plane(8, 4), Texture(seed + 20, (0.45, 0.55, 0.6), checker=10), static(UPRIGHT, (0, 3, 2))),
        Object(
            "left wall", Plane(8, 4), Texture(seed + 30, (0.6, 0.5, 0.55), checker=10), static(rot_z(math.pi / 2) @ UPRIGHT, (-3, 0, 2))
        ),
        Object(
            "right wall", Plane(8, 4), Texture(seed + 40, (0.5, 0.6, 0.45), checker=10), static(rot_z(-math.pi / 2) @ UPRIGHT, (3, 0, 2))
        ),
    ]


def die(seed: int) -> list[Object]:
    half = 0.25

    def pose(t: float) -> np.ndarray:
        theta = 3.0 * math.pi * t  # one and a half turns
        x = -1.0 + theta * half * 0.9
        z = half * (abs(math.cos(theta)) + abs(math.sin(theta)))  # lowest edge on the floor
        return rigid(rot_y(theta), (x, 0.0, z))

    return [Object("die", Box((half, half, half)), DieTexture(), pose, dynamic=True)]


BOUNCE_IMPACTS = (13.5 / 59, 35.5 / 59, 54.5 / 59)  # half-way between frames of the 60-frame default


def bounce(seed: int) -> list[Object]:
    r0, height, squash_w, squash_k = 0.28, 0.9, 0.012, 0.35
    edges = (-0.15,) + BOUNCE_IMPACTS + (1.2,)

    def squash(t: float) -> float:
        d = min(abs(t - ti) for ti in BOUNCE_IMPACTS)
        return squash_k * max(0.0, 1.0 - d / squash_w)

    def radii(t: float) -> np.ndarray:
        k = squash(t)
        return np.array([r0 * (1 + k / 2), r0 * (1 + k / 2), r0 * (1 - k)])

    def pose(t: float) -> np.ndarray:
        for a, b in zip(edges, edges[1:]):
            if a <= t <= b:
                break
        peak = height * (b - a) / 0.38  # shorter hops are lower
        z = r0 + 4 * peak * (t - a) * (b - t) / (b - a) ** 2  # velocity flips sign at impacts
        z += r0 * (1 - squash(t)) - r0
        x = -1.1 + 2.2 * t
        return rigid(rot_y(x / r0), (x, -0.2, z))

    return [Object("ball", Ellipsoid(radii), Texture(seed + 50, (0.85, 0.35, 0.2), checker=6, contrast=0.7), pose, dynamic=True)]


def top(seed: int) -> list[Object]:
    radii = np.array([0.34, 0.34, 0.16])

    def pose(t: float) -> np.ndarray:
        spin = 2 * math.pi * 8.0 * t  # eight turns over the sequence
        precess = 2 * math.pi * 1.0 * t
        tilt = rot_z(precess) @ rot_x(math.radians(12)) @ rot_z(-precess)
        centre = (0.35 * math.cos(2 * math.pi * t), 0.25 * math.sin(2 * math.pi * t), 0.18)
        return rigid(tilt @ rot_z(spin), centre)

    tex = Texture(seed + 60, (0.3, 0.4, 0.85), checker=12, contrast=0.8)
    return [Object("top", Ellipsoid(lambda _t: radii), tex, pose, dynamic=True)]


def sheet(seed: int) -> list[Object]:
    w, h, amp = 1.5, 1.1, 0.16

    def height_field(x, y, t):
        hang = 0.25 + 0.75 * np.clip(0.5 - y / h, 0, 1)  # the top edge barely moves
        return 0.13 * np.sin(2 * math.pi * (1.1 * x - 1.5 * t)) * hang

    return [
        Object(
            "sheet",
            Sheet(w, h, amp, height_field),
            Texture(seed + 70, (0.8, 0.75, 0.3), checker=10, contrast=0.8),
            static(UPRIGHT, (0, 0.4, 0.8)),
            dynamic=True,
        )
    ]


def cross(seed: int) -> list[Object]:
    def ball_pose(t):
        return rigid(rot_z(3 * t), (-1.3 + 2.6 * t, -0.4, 0.25))

    def box_pose(t):
        return rigid(rot_z(-2 * t), (1.3 - 2.6 * t, 0.5, 0.22))

    return [
        Object(
            "ball",
            Ellipsoid(lambda _t: np.array([0.25, 0.25, 0.25])),
            Texture(seed + 80, (0.9, 0.3, 0.3), checker=6),
            ball_pose,
            dynamic=True,
        ),
        Object("box", Box((0.22, 0.22, 0.22)), Texture(seed + 90, (0.3, 0.8, 0.4), checker=4), box_pose, dynamic=True),
    ]


def swing(seed: int) -> list[Object]:
    """A ball on a pendulum swinging parallel to the image plane of the training camera: fast
    in the middle of each swing, still at the ends, so the blur along the motion varies over
    time and across the sequence while the ball stays within ±0.5 of its rest point."""
    pivot, length, amp, periods = np.array([0.0, 0.0, 1.35]), 0.85, math.radians(35), 2.0

    def pose(t: float) -> np.ndarray:
        a = amp * math.sin(2 * math.pi * periods * t)
        R = rot_y(-a)
        return rigid(R, pivot + R @ np.array([0.0, 0.0, -length]))

    tex = Texture(seed + 120, (0.85, 0.3, 0.55), checker=6, contrast=0.8)
    return [Object("ball", Ellipsoid(lambda _t: np.array([0.2, 0.2, 0.2])), tex, pose, dynamic=True)]


def spin(seed: int) -> list[Object]:
    """A textured toy (a flat box, a different look on each face) spinning three turns about
    its own vertical axis while it drifts across a textured table: neighbouring points move in
    different directions and each one's path curves within a few frames, as a spinning toy
    filmed on a table does. The table is static; only the toy is dynamic."""
    table_top, half = 0.4, np.array([0.3, 0.17, 0.1])

    def pose(t: float) -> np.ndarray:
        return rigid(rot_z(2 * math.pi * 3.0 * t), (-0.45 + 0.9 * t, -0.2, table_top + half[2]))

    table = Object(
        "table",
        Box((0.95, 0.55, table_top / 2)),
        Texture(seed + 140, (0.55, 0.4, 0.3), checker=2, contrast=0.35),
        static(np.eye(3), (0.0, -0.1, table_top / 2)),
    )
    toy = Object("toy", Box(tuple(half)), Texture(seed + 150, (0.95, 0.8, 0.1), checker=3, contrast=0.7), pose, dynamic=True)
    return [table, toy]


def panel(seed: int, amplitude_deg: float = 20.0, size: float = 1.0) -> list[Object]:
    """A large textured panel hanging from a pivot above it and swinging in the image plane of
    the training camera (±20°, 1.5 periods): motion blur of several pixels along a direction
    and speed that vary across the panel (zero at the pivot, largest at the bottom edge), while
    every point moves less than a tenth of the panel's size per frame. `size` scales the panel,
    not its swing: a smaller panel moves further for its size."""
    pivot, drop, amp, periods = np.array([0.0, 0.2, 1.75]), 0.75, math.radians(amplitude_deg), 1.5

    def pose(t: float) -> np.ndarray:
        R = rot_y(-amp * math.sin(2 * math.pi * periods * t))
        return rigid(R @ UPRIGHT, pivot + R @ np.array([0.0, 0.0, -drop]))

    tex = Texture(seed + 130, (0.35, 0.65, 0.8), checker=8, contrast=0.8)
    return [Object("panel", Plane(1.1 * size, 0.9 * size), tex, pose, dynamic=True)]


def furniture(seed: int) -> list[Object]:
    return [
        Object("crate", Box((0.3, 0.25, 0.3)), Texture(seed + 100, (0.7, 0.5, 0.3), checker=5), static(rot_z(0.4), (-0.9, 0.9, 0.3))),
        Object(
            "globe",
            Ellipsoid(lambda _t: np.array([0.3, 0.3, 0.3])),
            Texture(seed + 110, (0.3, 0.5, 0.7), checker=8),
            static(np.eye(3), (1.0, 1.0, 0.3)),
        ),
    ]


SCENES: dict[str, Callable[[int], list[Object]]] = {
    "die": die,
    "bounce": bounce,
    "top": top,
    "sheet": sheet,
    "cross": cross,
    "swing": swing,
    "spin": spin,
    "panel": panel,
    # The same panel swinging ±40°: twice the speed, so twice the motion blur (at 128^2 and 30
    # frames, 4.9 px per frame interval on average inside the panel, 9.8 at the 95th percentile).
    "fastpanel": lambda seed: panel(seed, amplitude_deg=40.0),
    # fastpanel's swing with a panel about a third its size (18 px wide at 128^2, 1 % of the
    # frame): a small object's own motion blur, as a toy car's across a table; it moves its own
    # width in about four frames.
    "smallpanel": lambda seed: panel(seed, amplitude_deg=40.0, size=0.35),
    "room": lambda seed: [],
}


def build_world(name: str, seed: int) -> World:
    if name not in SCENES:
        raise ValueError(f"unknown synthetic scene {name!r}; choose from {', '.join(SCENES)}")
    return World(room(seed) + furniture(seed) + SCENES[name](seed))


# ---------------------------------------------------------------- cameras


def look_at(eye, target) -> np.ndarray:
    """World-to-camera (OpenCV axes) for a camera at `eye` looking at `target`, world z up."""
    return render_look_at(eye, target, up=(0.0, 0.0, 1.0), dtype=torch.float64).numpy()


def shaky_training_camera(seed: int, shake_deg: float = 0.6) -> Callable[[float], np.ndarray]:
    """A hand-held pan: a slow arc plus smooth shake (sums of sinusoids, continuous in t, so the
    shake also blurs within an exposure)."""
    rng = np.random.default_rng(seed + 1000)
    freqs = rng.uniform(4, 14, size=(3, 3))
    phases = rng.uniform(0, 2 * math.pi, size=(3, 3))
    amps = rng.uniform(0.5, 1.0, size=(3, 3)) / 3

    def viewmat(t: float) -> np.ndarray:
        eye = (-0.6 + 1.2 * t, -3.0, 1.4 + 0.1 * math.sin(2 * math.pi * t))
        V = look_at(eye, (0.0, 0.0, 0.45))
        ang = np.radians(shake_deg) * (amps * np.sin(2 * math.pi * freqs * t + phases)).sum(1)
        shake = rot_x(ang[0]) @ rot_y(ang[1]) @ rot_z(ang[2])
        out = V.copy()
        out[:3] = shake @ V[:3]  # rotate the camera frame about its own centre
        return out

    return viewmat


def heldout_camera() -> Callable[[float], np.ndarray]:
    V = look_at((0.45, -2.8, 1.2), (0.05, 0.0, 0.45))
    return lambda _t: V


def intrinsics(width: int, height: int, fov_x_deg: float = 55.0) -> np.ndarray:
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    return np.array([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1.0]])
