"""What the user chose in the viewer; the controls change it, the renderer reads it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class ViewerState:
    t: float = 0.0
    playing: bool = False
    speed: float = 1.0
    show_static: bool = True
    show_dynamic: bool = True
    overlay: int = 0  # 0 colours, 1 static/dynamic tint, 2 velocity-aligned ellipses
    stride: int = 4  # overlay density: every k-th dynamic splat
    arrows: bool = False
    tau: float = 2e-5
    exposure_captured: bool = False  # False: sharp; True: the run's exposure (as captured)
    lod: int | None = None
    mode: str = "orbit"  # orbit or fly
    viewmat: np.ndarray = field(default_factory=lambda: np.eye(4))
    K: np.ndarray = field(default_factory=lambda: np.eye(3))
    screenshot: str | None = None  # path requested by the screenshot button/command

    @property
    def show_mask(self) -> int:
        return (1 if self.show_static else 0) | (2 if self.show_dynamic else 0)
