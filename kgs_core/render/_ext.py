"""Builds (once) and loads the C++ rasteriser extension.

The extension is compiled with ninja through ``torch.utils.cpp_extension`` (by `kgs-app
build-ext`, which README's set-up runs, or on first use by a command that may build) and cached
under ``$KGS_CACHE_DIR/ext/<key>`` (default ``~/.cache/kinematics-gs``; ``$KGS_EXT_CACHE_DIR``
moves builds alone). The key hashes the
sources, the flags, the compiler, the torch and Python versions and installation, and the CPU
model, so a change to any of them rebuilds instead of loading a stale or illegal-instruction
binary. A finished build is marked with a stamp and from then on imported directly, without
running ninja: two ninjas (a virtual environment's and the system's) hash the same command
differently, and each would rebuild the other's build.

A process that must not build (the server and its jobs: ``KGS_EXT_BUILD=0``) loads a finished
build or gets `ExtensionUnavailable` naming the command to run.

torch guards a build with a lock file it waits on forever; a build killed half-way (Ctrl-C on
the first run) leaves that file behind and every later run hangs. So the build runs under our
own ``flock``, which the kernel drops when its holder dies: holding it, a torch lock file found
is stale and is removed.
"""

from __future__ import annotations

import fcntl
import hashlib
import importlib.util
import os
import platform
import shutil
import subprocess
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
CFLAGS = [
    "-O3",
    "-march=native",
    "-mprefer-vector-width=512",
    "-fopenmp",
    "-std=c++17",
    "-fno-math-errno",
    "-fno-trapping-math",
    "-Wno-psabi",
]
LDFLAGS = ["-fopenmp"]

_lock = threading.Lock()
_module: ModuleType | None = None
_error: Exception | None = None


class ExtensionUnavailable(RuntimeError):
    """The C++ backend cannot be built or loaded on this machine."""


def cache_root() -> Path:
    return Path(os.environ.get("KGS_CACHE_DIR", Path.home() / ".cache" / "kinematics-gs"))


def ext_root() -> Path:
    """Where builds live: `$KGS_EXT_CACHE_DIR`, else `cache_root()/ext`."""
    return Path(os.environ.get("KGS_EXT_CACHE_DIR") or cache_root() / "ext")


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


def _compiler_version() -> str:
    try:
        return subprocess.run([os.environ.get("CXX", "c++"), "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return ""


def build_key() -> str:
    h = hashlib.sha256()
    h.update(_compiler_version().encode())
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


def may_build() -> bool:
    """Whether this process may compile the extension (`KGS_EXT_BUILD=0`: the server, its jobs)."""
    return os.environ.get("KGS_EXT_BUILD", "1") != "0"


BUILD_COMMAND = "kgs-app build-ext"
STAMP = "built"  # written after a build that produced the library


def _import_built(build_dir: Path, name: str) -> ModuleType | None:
    """The library of a finished build in `build_dir`, imported without ninja; None if none."""
    library = build_dir / f"{name}.so"
    if not (build_dir / STAMP).is_file() or not library.is_file():
        return None
    spec = importlib.util.spec_from_file_location(name, library)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def built() -> bool:
    """Whether a finished build for this installation is in the cache (nothing is compiled)."""
    build_dir = ext_root() / build_key()
    return (build_dir / STAMP).is_file() and (build_dir / f"kgs_raster_{build_key()}.so").is_file()


def load(verbose: bool = False) -> ModuleType:
    """Returns the compiled extension, building it when this installation has none yet (about
    a minute on 2 cores) and this process may build."""
    global _module, _error
    with _lock:
        if _module is not None:
            return _module
        if _error is not None:
            raise ExtensionUnavailable(str(_error)) from _error
        key = build_key()
        name = f"kgs_raster_{key}"
        build_dir = ext_root() / key
        try:
            _module = _import_built(build_dir, name)
        except ImportError as exc:  # a damaged library: rebuilt below where allowed
            _module, damaged = None, exc
        else:
            damaged = None
        if _module is not None:
            return _module
        if not may_build():
            why = f"its library does not import ({damaged})" if damaged else "it is not built for this installation"
            _error = ExtensionUnavailable(f"the C++ rasteriser cannot be loaded: {why}; run `{BUILD_COMMAND}` first")
            raise _error
        if not compiler_available():
            _error = ExtensionUnavailable("no C++ compiler found (set CXX or install g++)")
            raise _error
        from torch.utils import cpp_extension

        build_dir.mkdir(parents=True, exist_ok=True)
        try:
            with _build_lock(build_dir):
                _module = _import_built(build_dir, name) if damaged is None else None  # another process built it
                if _module is None:
                    (build_dir / STAMP).unlink(missing_ok=True)
                    _module = cpp_extension.load(
                        name=name,
                        sources=[str(CSRC / s) for s in SOURCES],
                        extra_cflags=CFLAGS,
                        extra_ldflags=LDFLAGS,
                        build_directory=str(build_dir),
                        verbose=verbose,
                    )
                    (build_dir / STAMP).write_text(key)
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
