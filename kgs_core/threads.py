"""CPU placement: how many threads a process computes with, and how its idle OpenMP threads wait.

torch and the C++ rasteriser share one OpenMP runtime (libgomp), which reads its settings from
the environment once, when torch is imported. So `configure_process` runs first thing in every
entry point (`kgs-app`, the server's job processes), and the server's job runner starts each
job with `placement_env` for its share of the machine.

Measured in docs/results.md, "Sharing the CPU" (`kgs-app bench threads`): a short spin
(SPIN_COUNT) is the fastest alone (libgomp's default spins 300,000 times before a waiting
thread sleeps); no wait policy makes two multi-threaded trainings share two cores well, a
thread count that follows the load does (ThreadTuner).

`KGS_THREADS=N` gives a process N threads; `KGS_THREADS=off` leaves the environment alone
(libgomp's and torch's own defaults). An `OMP_NUM_THREADS` or `GOMP_SPINCOUNT` already set
wins over these.
"""

from __future__ import annotations

import os
import sys

SPIN_COUNT = 10_000  # libgomp spins before a waiting thread sleeps (default 300,000)


def cores_available() -> int:
    """The CPUs this process may run on (its affinity mask; a container's limit shows there)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def placement_env(cores: int) -> dict[str, str]:
    """The environment for a process given `cores` CPUs."""
    return {"OMP_NUM_THREADS": str(max(1, int(cores))), "GOMP_SPINCOUNT": str(SPIN_COUNT)}


def placement_off() -> bool:
    """`KGS_THREADS=off`: leave OpenMP's and torch's own defaults alone."""
    return os.environ.get("KGS_THREADS", "").strip().lower() == "off"


def requested_cores() -> int | None:
    """`KGS_THREADS` as a number of cores: None when unset, "off" or not a positive number."""
    raw = os.environ.get("KGS_THREADS", "").strip()
    return int(raw) if raw.isdigit() and int(raw) > 0 else None


def cores_to_use() -> int:
    """The cores this process computes on: `KGS_THREADS` when it names a number, else every
    available one."""
    return requested_cores() or cores_available()


def omp_threads() -> int | None:
    """`OMP_NUM_THREADS` as a count: None when unset or not a plain number (e.g. a nested "4,2")."""
    raw = os.environ.get("OMP_NUM_THREADS", "").strip()
    return int(raw) if raw.isdigit() and int(raw) > 0 else None


def configure_process() -> int | None:
    """Sets this process's placement from `KGS_THREADS` (else every available core), before
    torch is imported where possible; returns the thread count, None when left alone."""
    if placement_off():
        return None
    if "KGS_OMP_FROM_USER" not in os.environ:  # inherited by child processes: set once, at the top
        os.environ["KGS_OMP_FROM_USER"] = "1" if "OMP_NUM_THREADS" in os.environ else "0"
    for key, value in placement_env(cores_to_use()).items():
        os.environ.setdefault(key, value)
    threads = omp_threads()
    if threads and "torch" in sys.modules:  # too late for libgomp's wait policy, not for the count
        sys.modules["torch"].set_num_threads(threads)
    return threads


def parallel_map(fn, items: list, desc: str | None = None, progress: bool = False) -> list:
    """`[fn(x) for x in items]` on a thread per core (`KGS_THREADS`, else the available cores),
    in order; with `desc`, a progress bar under that name. For per-frame work in libraries that
    release the GIL (PIL's resampling and PNG encoding, numpy, pycolmap's undistortion): on
    two cores ingest's decoding and writing of 672 frames took half the time (docs/data.md)."""
    from concurrent.futures import ThreadPoolExecutor

    from .progress import progress_bar

    with ThreadPoolExecutor(min(cores_to_use(), max(1, len(items)))) as pool:
        results = pool.map(fn, items)
        if desc is None:
            return list(results)
        with progress_bar(results, total=len(items), desc=desc, show=progress) as bar:
            return list(bar)


def machine_busy_seconds() -> float | None:
    """CPU seconds all processes have used on this machine since boot (`/proc/stat`: every
    state but idle and iowait, summed over the CPUs); None where there is no /proc/stat."""
    try:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)
    return (sum(fields) - idle) / os.sysconf("SC_CLK_TCK")


class ThreadTuner:
    """Keeps a training's thread count at the cores that nothing else is using.

    OpenMP splits every parallel loop statically between the threads and waits for all of
    them, so a thread whose core another process holds delays every loop by a time slice: two
    2-thread trainings on two cores, or one beside a busy process, ran 3.5-6x slower than alone
    (docs/results.md, "Sharing the CPU"). Waiting passively helps sharing but costs 50 %
    alone; one thread each is the fastest shared, all the cores alone. What else runs changes
    while a training runs and nobody tells the process, so it is measured, at no cost: over
    each `window_s`, the machine's busy CPU time (`machine_busy_seconds`) minus this process's
    own is what the others use, in cores; the thread count becomes the cores left, at least one.
    Two tuned trainings settle at one thread each; the one left takes the cores back.

    `observe()` after each step (the trainer calls it); the clocks are arguments for tests."""

    def __init__(
        self, cores: int, start: int | None = None, window_s: float = 0.5, machine_busy=machine_busy_seconds, own_cpu=None, clock=None
    ):
        import time

        import torch

        self._torch = torch
        self.cores, self.window_s = max(1, cores), window_s
        self._machine_busy, self._own_cpu = machine_busy, own_cpu or time.process_time
        self._clock = clock or time.perf_counter
        self.current = min(self.cores, start or self.cores)
        self.changes = 0
        self.others = 0.0  # the other processes' use in the last window, in cores
        self._set(self.current)
        self._mark()

    def _mark(self) -> None:
        self._t0, self._own0, self._busy0 = self._clock(), self._own_cpu(), self._machine_busy()

    def _set(self, n: int) -> None:
        if self._torch.get_num_threads() != n:
            self._torch.set_num_threads(n)

    def observe(self, step_seconds: float | None = None) -> None:
        """After a training step: at the end of each window, the next steps' thread count."""
        elapsed = self._clock() - self._t0
        if elapsed < self.window_s:
            return
        busy, own = self._machine_busy(), self._own_cpu()
        if busy is not None and self._busy0 is not None:
            self.others = max(0.0, (busy - self._busy0) - (own - self._own0)) / elapsed
            # + 0.25: a core the others use a quarter of is still ours (jiffy noise, short tasks).
            target = min(self.cores, max(1, int(self.cores - self.others + 0.25)))
            if target != self.current:
                self.current = target
                self.changes += 1
                self._set(target)
        self._mark()


def tuner_for_process(start: int | None = None) -> ThreadTuner | None:
    """A ThreadTuner over every available core for a training in this process, starting at
    `start` threads (default: all); None when the count was fixed (`KGS_THREADS=N` or `off`,
    or an `OMP_NUM_THREADS` set outside) or there is one core."""
    fixed = os.environ.get("KGS_THREADS", "").strip() != "" or os.environ.get("KGS_OMP_FROM_USER") == "1"
    if fixed or cores_available() < 2:
        return None
    return ThreadTuner(cores_available(), start)
