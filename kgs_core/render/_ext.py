"""Builds (once) and loads the C++ rasteriser extension.

The extension is compiled on first use with ninja through ``torch.utils.cpp_extension`` and
cached under ``$KGS_CACHE_DIR/ext/<key>`` (default ``~/.cache/kinematics-gs``). The key
hashes the sources, the flags, the torch and Python versions and installation, and the CPU
model, so a change to any of them rebuilds instead of loading a stale or illegal-instruction
binary (and two virtual environments do not rebuild each other's: ninja's command line holds
each one's include paths).

torch guards a build with a lock file it waits on forever; a build killed half-way (Ctrl-C on
the first run) leaves that file behind and every later run hangs. So the build runs under our
own ``flock``, which the kernel drops when its holder dies: holding it, a torch lock file found
is stale and is removed.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import platform
import shutil
import sys
import threading
from pathlib import Path
from types import ModuleType

import torch

CSRC = Path(__file__).parent / "csrc"
SOURCES = ["bindings.cpp", "covariance.cpp", "project.cpp", "binning.cpp", "raster.cpp", "sh.cpp", "ssim.cpp", "kplanes.cpp"]
HEADERS = ["kernels.h", "simd.h", "parallel.h"]
# -fno-trapping-math: nothing here reads floating-point exception flags, and it lets GCC
# evaluate both sides of a select, which the vectorised projection backward needs on AVX2.
CFLAGS = ["-O3", "-march=native", "-mprefer-vector-width=512", "-fopenmp", "-std=c++17", "-fno-math-errno",
          "-fno-trapping-math", "-Wno-psabi"]
LDFLAGS = ["-fopenmp"]

_lock = threading.Lock()
_module: ModuleType | None = None
_error: Exception | None = None


class ExtensionUnavailable(RuntimeError):
    """The C++ backend cannot be built or loaded on this machine."""


def cache_root() -> Path:
    return Path(os.environ.get("KGS_CACHE_DIR", Path.home() / ".cache" / "kinematics-gs"))


def _cpu_model() -> str:
    """The first CPU's model name and instruction-set flags: a virtual machine may report
    only "AMD EPYC" for generations with and without AVX-512, so the name alone is not enough."""
    try:
        lines = Path("/proc/cpuinfo").read_text().split("\n\n", 1)[0].splitlines()
        picked = [line for line in lines if line.startswith(("model name", "flags"))]
        if picked:
            return "\n".join(picked)
    except OSError:
        pass
    return platform.processor()


def build_key() -> str:
    h = hashlib.sha256()
    for name in SOURCES + HEADERS:
        h.update(name.encode())
        h.update((CSRC / name).read_bytes())
    h.update(" ".join(CFLAGS + LDFLAGS).encode())
    h.update(torch.__version__.encode())
    h.update(str(Path(torch.__file__).resolve().parent).encode())
    h.update(sys.version.encode())
    h.update(_cpu_model().encode())
    return h.hexdigest()[:16]


def compiler_available() -> bool:
    return shutil.which(os.environ.get("CXX", "c++")) is not None


def load(verbose: bool = False) -> ModuleType:
    """Returns the compiled extension, building it on first use (about a minute on 2 cores)."""
    global _module, _error
    with _lock:
        if _module is not None:
            return _module
        if _error is not None:
            raise ExtensionUnavailable(str(_error)) from _error
        if not compiler_available():
            _error = ExtensionUnavailable("no C++ compiler found (set CXX or install g++)")
            raise _error
        from torch.utils import cpp_extension

        key = build_key()
        build_dir = cache_root() / "ext" / key
        build_dir.mkdir(parents=True, exist_ok=True)
        try:
            with _build_lock(build_dir):
                _module = cpp_extension.load(
                    name=f"kgs_raster_{key}",
                    sources=[str(CSRC / s) for s in SOURCES],
                    extra_cflags=CFLAGS,
                    extra_ldflags=LDFLAGS,
                    build_directory=str(build_dir),
                    verbose=verbose,
                )
        except Exception as exc:  # compiler errors, missing ninja, ...
            _error = exc
            raise ExtensionUnavailable(f"building the C++ rasteriser failed: {exc}") from exc
        return _module


class _build_lock:
    """`with _build_lock(build_dir)`: an exclusive flock on `build_dir/kgs.lock`, held for the
    build; once held, torch's own `lock` file there can only be a killed build's, and goes."""

    def __init__(self, build_dir: Path):
        self.path = build_dir / "kgs.lock"

    def __enter__(self):
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        fcntl.flock(self.fd, fcntl.LOCK_EX)
        (self.path.parent / "lock").unlink(missing_ok=True)
        return self

    def __exit__(self, *exc):
        fcntl.flock(self.fd, fcntl.LOCK_UN)
        os.close(self.fd)


def usable_for(t) -> bool:
    """Whether the compiled kernels can take tensor `t`: a CPU tensor and an extension that
    builds/loads here (pure-PyTorch fallbacks are used otherwise)."""
    if t.device.type != "cpu":
        return False
    try:
        load()
    except ExtensionUnavailable:
        return False
    return True
