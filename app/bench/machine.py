"""The one-line machine description every benchmark prints above its numbers."""

from __future__ import annotations

import os
import platform

import torch


def simd_path() -> str:
    """The float SIMD code the C++ extension was compiled with ("avx512", "avx2", "generic"):
    the same kernels differ several-fold between them, so every timing names it."""
    from kgs_core.render import _ext

    try:
        return _ext.load().simd_path()
    except _ext.ExtensionUnavailable:
        return "none (no C++ extension)"


def machine() -> str:
    cpu = platform.processor() or "unknown cpu"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, rasteriser SIMD {simd_path()}, torch {torch.__version__} ({torch.get_num_threads()} threads)"
