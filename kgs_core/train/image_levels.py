"""Coarse-to-fine training images (`TrainConfig.downscales`): the size a step trains at, and a
training frame's camera, image and optical flow at that size.

A level's image is the full frame area-averaged over k x k pixels (k = 2^level), so it is what a
camera of k times larger pixels would record; its camera is the same pose with the intrinsics
divided by k (pixel centres at +0.5 stay centred); its flow is the full-size flow averaged the
same way, in the level's pixels. The frame is cropped to a multiple of k first, which leaves K's
principal point where it is.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch
import torch.nn.functional as F
from torch import Tensor

from ..data.scene import Camera, Frame


def image_divisor(it: int, iterations: int, downscales: int, until: float) -> int:
    """The divisor of the image size at step `it`: 2^downscales from the start, halved at equal
    shares of the first `until` of the `iterations`, 1 from there on."""
    end = until * iterations
    if downscales <= 0 or it >= end:
        return 1
    return 2 ** (downscales - int(it * downscales / end))


def divisor_changes(iterations: int, downscales: int, until: float) -> list[int]:
    """The steps at which `image_divisor` changes (each the first step at its new size)."""
    if downscales <= 0:
        return []
    end = until * iterations
    steps = {min(iterations, math.ceil(j * end / downscales)) for j in range(1, downscales + 1)}
    return sorted(s for s in steps if 0 < s < iterations)


def level_camera(cam: Camera, k: int) -> Camera:
    """`cam` for its image cropped to a multiple of `k` and area-averaged by `k`."""
    if k == 1:
        return cam
    return replace(cam.scaled(1.0 / k), width=cam.width // k, height=cam.height // k)


def area_average(x: Tensor, k: int) -> Tensor:
    """`x` (H, W, C) cropped to a multiple of `k` and averaged over k x k blocks (NaN spreads
    to its block: a flow that failed its check anywhere in a block fails in the level)."""
    if k == 1:
        return x
    h, w = x.shape[0] // k, x.shape[1] // k
    blocks = x[: h * k, : w * k].permute(2, 0, 1)[None]
    return F.avg_pool2d(blocks, k)[0].permute(1, 2, 0).contiguous()


class LevelViews:
    """Each training frame's camera, image and flow at a divisor `k`, made once and kept (the
    full-size ones are the scene's, the cache's and the flows' own)."""

    def __init__(self, images, flows: dict[str, tuple[int, Tensor]]):
        self.images, self.flows = images, flows
        self._made: dict[tuple[str, str, int], object] = {}

    def _once(self, kind: str, frame: Frame, k: int, make):
        key = (kind, frame.id, k)
        if key not in self._made:
            self._made[key] = make()
        return self._made[key]

    def camera(self, frame: Frame, k: int) -> Camera:
        return frame.camera if k == 1 else self._once("camera", frame, k, lambda: level_camera(frame.camera, k))

    def image(self, frame: Frame, k: int) -> Tensor:
        full = self.images.get(frame)
        return full if k == 1 else self._once("image", frame, k, lambda: area_average(full, k))

    def flow(self, frame: Frame, k: int) -> tuple[int, Tensor]:
        """`(index of the next frame, flow (H/k, W/k, 2) in the level's pixels)`."""
        j, full = self.flows[frame.id]
        if k == 1:
            return j, full
        return j, self._once("flow", frame, k, lambda: area_average(torch.as_tensor(full), k) / k)
