"""The non-destructive edit layer of a run: Gaussians hidden or deleted in a viewer, and a crop
box. Stored beside the model as `RUN/edits.json`; the model itself is never modified, and every
consumer (exports, the server, the viewers) asks `keep_mask` which Gaussians to use.

```json
{"format_version": 1,
 "levels": {"3": {"deleted": [12, 40], "hidden": [7]}},
 "crop": {"min": [-1, -1, -1], "max": [1, 1, 1]}}
```

Every change keeps the layer it replaced under `history.undo` (with a label such as "delete 12
splats"; at most HISTORY_LIMIT steps), and an undo moves it back, keeping the undone one under
`history.redo` until the next change: so an undo survives a reload, a crop included.

Indices are per LoD level (each level has its own Gaussians). `hidden` is what a viewer toggles
off for a while, `deleted` what the user removed; both are left out of exports, and clearing the
layer restores everything. The crop box tests the *canonical* centres, so a moving Gaussian does
not pop in and out of the crop as it moves.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .io import atomic_write_text

EDITS_FORMAT_VERSION = 1
EDITS_FILE = "edits.json"
HISTORY_LIMIT = 50  # undo steps kept


class EditsError(ValueError):
    pass


@dataclass
class LevelEdits:
    deleted: set[int] = field(default_factory=set)
    hidden: set[int] = field(default_factory=set)


@dataclass
class EditLayer:
    levels: dict[int, LevelEdits] = field(default_factory=dict)
    crop_min: np.ndarray | None = None  # (3,)
    crop_max: np.ndarray | None = None  # (3,)
    # Earlier and undone layers, oldest first: [{"label": str, "layer": to_dict() without history}]
    undo: list[dict] = field(default_factory=list)
    redo: list[dict] = field(default_factory=list)

    @property
    def empty(self) -> bool:
        return self.crop_min is None and not any(e.deleted or e.hidden for e in self.levels.values())

    def level(self, level: int) -> LevelEdits:
        return self.levels.setdefault(int(level), LevelEdits())

    def keep_mask(self, level: int, canonical_means: np.ndarray, include_hidden: bool = False) -> np.ndarray:
        """`(N,)` bool: the Gaussians of LoD `level` that survive the edits. Hidden ones are
        dropped unless `include_hidden` (a viewer showing them greyed out)."""
        n = len(canonical_means)
        keep = np.ones(n, dtype=bool)
        e = self.levels.get(int(level))
        if e is not None:
            drop = set(e.deleted) | (set() if include_hidden else set(e.hidden))
            bad = [i for i in drop if not 0 <= i < n]
            if bad:
                raise EditsError(
                    f"{EDITS_FILE}: level {level} names Gaussians {sorted(bad)[:5]} outside 0..{n - 1} (edits made for another model?)"
                )
            if drop:
                keep[np.fromiter(drop, dtype=np.int64)] = False
        if self.crop_min is not None:
            inside = np.all((canonical_means >= self.crop_min) & (canonical_means <= self.crop_max), axis=1)
            keep &= inside
        return keep

    def to_dict(self) -> dict:
        d: dict = {
            "format_version": EDITS_FORMAT_VERSION,
            "levels": {
                str(k): {"deleted": sorted(v.deleted), "hidden": sorted(v.hidden)}
                for k, v in sorted(self.levels.items())
                if v.deleted or v.hidden
            },
        }
        d["crop"] = None if self.crop_min is None else {"min": self.crop_min.tolist(), "max": self.crop_max.tolist()}
        if self.undo or self.redo:
            d["history"] = {"undo": self.undo, "redo": self.redo}
        return d

    def state(self) -> dict:
        """The layer without its history (what a history step holds)."""
        d = self.to_dict()
        d.pop("history", None)
        return d

    def changed(self, label: str) -> "EditLayer":
        """The layer that a change labelled `label` starts from: this one's edits, with this
        state pushed onto the undo history and the redo history dropped."""
        out = EditLayer.from_dict(self.state())
        out.undo = [*self.undo, {"label": label, "layer": self.state()}][-HISTORY_LIMIT:]
        return out

    def step(self, back: bool) -> "EditLayer":
        """The layer after an undo (`back`) or a redo; EditsError when there is none."""
        source = self.undo if back else self.redo
        if not source:
            raise EditsError(f"nothing to {'undo' if back else 'redo'}")
        entry = source[-1]
        out = EditLayer.from_dict(entry["layer"], "history")
        mine = {"label": entry["label"], "layer": self.state()}
        out.undo = self.undo[:-1] if back else [*self.undo, mine][-HISTORY_LIMIT:]
        out.redo = [*self.redo, mine] if back else self.redo[:-1]
        return out

    def history_labels(self) -> dict:
        """{"undo": label of the step an undo reverts or None, "redo": likewise, counts}."""
        return {
            "undo": self.undo[-1]["label"] if self.undo else None,
            "undo_steps": len(self.undo),
            "redo": self.redo[-1]["label"] if self.redo else None,
            "redo_steps": len(self.redo),
        }

    @classmethod
    def from_dict(cls, d: dict, source: str = EDITS_FILE) -> "EditLayer":
        if not isinstance(d, dict):
            raise EditsError(f"{source}: expected a JSON object")
        if d.get("format_version", EDITS_FORMAT_VERSION) != EDITS_FORMAT_VERSION:
            raise EditsError(f"{source}: format_version {d.get('format_version')} not supported")
        layer = cls()
        levels = d.get("levels") or {}
        if not isinstance(levels, dict):
            raise EditsError(f"{source}: 'levels' must be an object keyed by LoD level")
        for key, val in levels.items():
            try:
                lvl = int(key)
            except ValueError:
                raise EditsError(f"{source}: level key {key!r} is not an integer") from None
            if not isinstance(val, dict):
                raise EditsError(f"{source}: levels.{key} must be an object")
            e = layer.level(lvl)
            for name in ("deleted", "hidden"):
                ids = val.get(name, [])
                if not isinstance(ids, list) or not all(isinstance(i, int) and not isinstance(i, bool) for i in ids):
                    raise EditsError(f"{source}: levels.{key}.{name} must be a list of integers")
                getattr(e, name).update(ids)
        crop = d.get("crop")
        if crop is not None:
            try:
                lo = np.asarray(crop["min"], dtype=np.float64)
                hi = np.asarray(crop["max"], dtype=np.float64)
            except (KeyError, TypeError, ValueError):
                raise EditsError(f"{source}: crop must be {{'min': [x, y, z], 'max': [x, y, z]}}") from None
            if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()):
                raise EditsError(f"{source}: crop.min and crop.max must be 3 finite numbers each")
            if np.any(lo > hi):
                raise EditsError(f"{source}: crop.min must not exceed crop.max")
            layer.crop_min, layer.crop_max = lo, hi
        history = d.get("history")
        if history is not None:
            if not isinstance(history, dict):
                raise EditsError(f"{source}: history must be {{'undo': [...], 'redo': [...]}}")
            for name in ("undo", "redo"):
                steps = history.get(name, [])
                if (
                    not isinstance(steps, list)
                    or len(steps) > HISTORY_LIMIT
                    or not all(
                        isinstance(st, dict)
                        and isinstance(st.get("label"), str)
                        and isinstance(st.get("layer"), dict)
                        and "history" not in st["layer"]
                        for st in steps
                    )
                ):
                    raise EditsError(
                        f"{source}: history.{name} must be at most {HISTORY_LIMIT} {{'label': text, 'layer': edits without history}} steps"
                    )
                for k, st in enumerate(steps):  # each step must itself be a valid layer
                    cls.from_dict(st["layer"], f"{source}: history.{name}[{k}]")
                setattr(layer, name, [{"label": st["label"][:200], "layer": st["layer"]} for st in steps])
        return layer


def load_edits(run_dir: str | Path) -> EditLayer:
    path = Path(run_dir) / EDITS_FILE
    if not path.is_file():
        return EditLayer()
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise EditsError(f"{path}: invalid JSON ({exc.msg})") from None
    return EditLayer.from_dict(d, str(path))


def save_edits(run_dir: str | Path, layer: EditLayer) -> Path:
    return atomic_write_text(Path(run_dir) / EDITS_FILE, json.dumps(layer.to_dict(), indent=1))
