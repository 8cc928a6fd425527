"""Progress of long work, for a person at a terminal and for a program watching.

`progress_bar` is a tqdm bar (drawn only when `show`) that also tells the listeners registered
with `listen` how far its stage is; `announce` names a stage that has no count (a mapper run).
The server's job process listens and writes what it hears to a file the browser polls
(backend/worker.py), so the same stages show in the terminal and in the UI.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Callable, Iterable, Iterator

from tqdm import tqdm

Listener = Callable[[str, int, "int | None"], None]  # (stage, done, total or None)
_listeners: list[Listener] = []


@contextmanager
def listen(fn: Listener) -> Iterator[None]:
    """Calls `fn(stage, done, total)` at every bar update and announcement in the block."""
    _listeners.append(fn)
    try:
        yield
    finally:
        _listeners.remove(fn)


def announce(stage: str, done: int = 0, total: int | None = None) -> None:
    for fn in list(_listeners):
        fn(stage, done, total)


class ProgressBar:
    """A tqdm bar whose counts also go to the listeners, under the name `stage`. Iterate over it
    (each item counts one) or call `update(n)`; use it as a context manager or `close()` it."""

    def __init__(self, iterable: Iterable | None, total: int | None, desc: str, unit: str, show: bool, stage: str):
        self.iterable, self.total, self.stage, self.n = iterable, total, stage, 0
        self._bar = tqdm(total=total, desc=desc, unit=unit, disable=not show)
        announce(stage, 0, total)

    def update(self, n: int = 1) -> None:
        self.n += n
        self._bar.update(n)
        announce(self.stage, self.n, self.total)

    def __iter__(self):
        for item in self.iterable:
            yield item
            self.update()

    def close(self) -> None:
        self._bar.close()

    def __enter__(self) -> "ProgressBar":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def progress_bar(
    iterable: Iterable | None = None,
    *,
    total: int | None = None,
    desc: str,
    unit: str = "frame",
    show: bool = True,
    stage: str | None = None,
) -> ProgressBar:
    """`desc` labels the terminal's bar; `stage` (default: `desc`) is what listeners hear, for
    when the bar names something a listener should not see, such as a file path."""
    if total is None and iterable is not None and hasattr(iterable, "__len__"):
        total = len(iterable)
    return ProgressBar(iterable, total, desc, unit, show, stage or desc)
