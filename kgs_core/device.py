"""Which device a command computes on (`--device auto|cpu|cuda`, `TrainConfig.device`).

The CPU path is the product's own (the C++ rasteriser, K-Planes sampler and SSIM); on CUDA the
rasteriser is gsplat's (`render/gsplat_backend.py`, the `kinematics-gs[cuda]` extra) and the
rest runs as PyTorch on the GPU. `auto` takes CUDA when torch sees a device."""

from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator, Literal

import torch

Device = Literal["auto", "cpu", "cuda"]
DEVICES = ("auto", "cpu", "cuda")
CUDA_EXTRA = "pip install 'kinematics-gs[cuda]'"


class DeviceError(ValueError):
    """A device that cannot be used here, said in words that name the option."""


def resolve_device(name: str, option: str = "--device") -> torch.device:
    """`torch.device` for `name` (auto, cpu, cuda or cuda:N); DeviceError naming `option` when
    CUDA is asked for and torch sees none, or when the name is not a device."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name == "cuda" or (name.startswith("cuda:") and name[5:].isdigit()):
        if not torch.cuda.is_available():
            build = torch.version.cuda
            why = "this torch is a CPU build" if build is None else f"torch (CUDA {build}) sees no GPU"
            raise DeviceError(f"{option} {name}: {why}; use --device cpu or auto")
        index = int(name[5:]) if ":" in name else 0
        if index >= torch.cuda.device_count():
            raise DeviceError(f"{option} {name}: only {torch.cuda.device_count()} CUDA device(s)")
        return torch.device("cuda", index)
    raise DeviceError(f"{option} must be one of {', '.join(DEVICES)} (or cuda:N), got {name!r}")


@contextmanager
def computing_on(device: torch.device) -> Iterator[None]:
    """Tensors made without a device inside land on `device` (a no-op on the CPU)."""
    if device.type == "cpu":
        yield
        return
    with device:
        yield


def tensors_to(obj, device: torch.device):
    """`obj` (a saved model or checkpoint: dicts, lists and tuples of tensors and plain values)
    with every tensor on `device`; the same object on the CPU."""
    if device.type == "cpu":
        return obj
    if isinstance(obj, torch.Tensor):
        return obj.to(device)
    if isinstance(obj, dict):
        return {k: tensors_to(v, device) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(tensors_to(v, device) for v in obj)
    return obj
