"""Reading and writing the image-like files of a dataset, with errors that name the file."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..io import atomic_write_bytes


class ImageError(ValueError):
    pass


# The most pixels a dataset image may hold (a 4096 x 4096 frame). Checked from the header,
# before anything is decoded: a small compressed file can claim gigabytes of pixels.
MAX_IMAGE_PIXELS = 4096 * 4096


def _bounded(im: Image.Image, path: Path) -> None:
    w, h = im.size
    if w * h > MAX_IMAGE_PIXELS:
        raise ImageError(f"image {path.name} is {w}x{h}, above the {MAX_IMAGE_PIXELS:,} pixels a frame may hold")


def read_image(path: str | Path) -> np.ndarray:
    """`(H, W, 3)` float32 in [0, 1]; alpha, if any, is composited over black."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            _bounded(im, path)
            im.load()
            if im.mode in ("RGBA", "LA"):
                arr = np.asarray(im.convert("RGBA"), dtype=np.float32) / 255.0
                return np.ascontiguousarray(arr[..., :3] * arr[..., 3:4])
            mode_max = 65535.0 if im.mode.startswith("I;16") else 255.0
            if mode_max > 255:
                return np.repeat((np.asarray(im, dtype=np.float32) / mode_max)[..., None], 3, axis=-1)
            return np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    except FileNotFoundError:
        raise ImageError(f"image file not found: {path}") from None
    except (UnidentifiedImageError, OSError, SyntaxError, Image.DecompressionBombError) as exc:
        raise ImageError(f"cannot read image {path}: {exc}") from None


def read_mask(path: str | Path) -> np.ndarray:
    """`(H, W)` bool from an 8-bit image (non-zero = set)."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            _bounded(im, path)
            return np.asarray(im.convert("L")) > 127
    except FileNotFoundError:
        raise ImageError(f"mask file not found: {path}") from None
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as exc:
        raise ImageError(f"cannot read mask {path}: {exc}") from None


def read_motion(path: str | Path) -> np.ndarray:
    """`(H, W, 2)` float32 image motion in pixels per frame interval (`.npy`)."""
    path = Path(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise ImageError(f"motion file not found: {path}") from None
    except (ValueError, OSError) as exc:
        raise ImageError(f"cannot read motion {path}: {exc}") from None
    if arr.ndim != 3 or arr.shape[-1] != 2:
        raise ImageError(f"motion {path}: expected (H, W, 2), got {arr.shape}")
    return arr.astype(np.float32)


def to_uint8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def png_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG")
    return buf.getvalue()


def write_image(path: str | Path, img: np.ndarray) -> None:
    """Writes `(H, W, 3)` float in [0, 1] as an 8-bit PNG."""
    atomic_write_bytes(path, png_bytes(to_uint8(img)))


def write_mask(path: str | Path, mask: np.ndarray) -> None:
    atomic_write_bytes(path, png_bytes((mask.astype(np.uint8) * 255)))


def write_motion(path: str | Path, motion: np.ndarray) -> None:
    buf = io.BytesIO()
    np.save(buf, motion.astype(np.float32))
    atomic_write_bytes(path, buf.getvalue())
