"""The server's cache of loaded runs (`RunView`, in `kgs_core.run_view`)."""

from __future__ import annotations

import threading
from collections import OrderedDict
from pathlib import Path

from kgs_core.run_view import RunView


class RunViews:
    """A small LRU of loaded runs (models are tens of MB)."""

    def __init__(self, capacity: int = 4):
        self.capacity = capacity
        self.views: OrderedDict[str, RunView] = OrderedDict()
        self.lock = threading.Lock()

    def get(self, run_id: str, run_dir: Path) -> RunView:
        with self.lock:
            v = self.views.get(run_id)
            if v is not None:
                self.views.move_to_end(run_id)
                return v
        v = RunView(run_dir)  # outside the lock: loading takes a moment
        with self.lock:
            self.views[run_id] = v
            while len(self.views) > self.capacity:
                self.views.popitem(last=False)
        return v

    def loaded(self, run_id: str) -> RunView | None:
        """The run's view if it is loaded, without touching the workspace or the disk."""
        with self.lock:
            return self.views.get(run_id)

    def drop(self, run_id: str) -> None:
        with self.lock:
            self.views.pop(run_id, None)
