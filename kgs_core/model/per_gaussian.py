"""The per-Gaussian state beside the parameters, declared once and resized in lock-step.

Every field has one row per Gaussian. `PerGaussian` keeps them together so that pruning
(`select`), densification (`append`), saving (`state`) and loading (`from_state`, with each
field checked and the ones absent from older runs filled in) treat every field alike: a new
per-Gaussian quantity is one entry in `FIELDS` and one attribute below, nothing else.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Callable

import torch
from torch import Tensor


def unbounded_lifespan(n: int) -> Tensor:
    """`(n, 2)` lifespans of Gaussians present at every time (centre 0, width inf)."""
    return torch.tensor([0.0, float("inf")]).repeat(n, 1)


def _finite(t: Tensor) -> bool:
    return bool(torch.isfinite(t).all())


def _lifespan_ok(t: Tensor) -> bool:
    # A NaN or non-positive width would make NaN opacities deep in the renderer.
    return t.dtype.is_floating_point and bool(torch.isfinite(t[:, 0]).all()) and bool((t[:, 1] > 0).all())


@dataclass(frozen=True)
class Field:
    """How one per-Gaussian field looks: its shape after the Gaussian axis, its fill for `n` new
    Gaussians (also what a run saved before the field existed gets), and a check of its values."""

    tail: tuple[int, ...]
    empty: Callable[[int], Tensor]
    ok: Callable[[Tensor], bool]
    expected: str  # what `ok` wants, for the error message
    since_start: bool = True  # in every saved model; False: absent from runs saved before it existed


FIELDS: dict[str, Field] = {
    "dynamic": Field((), lambda n: torch.zeros(n, dtype=torch.bool), lambda t: t.dtype == torch.bool, "a bool mask"),
    "K": Field((), lambda n: torch.zeros(n), lambda t: t.dtype.is_floating_point, "floats (K)"),
    "lifespan": Field(
        (2,), unbounded_lifespan, _lifespan_ok, "floats, finite centres and widths > 0 (inf: always present)", since_start=False
    ),
    "own_velocity": Field(
        (3,), lambda n: torch.zeros(n, 3), lambda t: t.dtype.is_floating_point and _finite(t), "finite floats", since_start=False
    ),
}


@dataclass
class PerGaussian:
    """`dynamic (N,) bool`: deformed by the field (the decomposition by K); `K (N,)`: the
    temporal variance of its offsets; `lifespan (N, 2)`: time of presence (centre, width in
    normalised time; width inf, the paper's Gaussians: present at every time; spawned ones live
    around their frame); `own_velocity (N, 3)`: the world velocity of a Gaussian with a bounded
    lifespan under `spawned_motion="own"` (zeros, and unread, for the others)."""

    dynamic: Tensor
    K: Tensor
    lifespan: Tensor
    own_velocity: Tensor

    @classmethod
    def empty(cls, n: int) -> "PerGaussian":
        return cls(**{name: f.empty(n) for name, f in FIELDS.items()})

    def __len__(self) -> int:
        return len(self.dynamic)

    def items(self):
        return ((f.name, getattr(self, f.name)) for f in fields(self))

    def select(self, keep: Tensor) -> "PerGaussian":
        """The rows `keep` (a bool mask or indices) of every field."""
        return PerGaussian(**{name: value[keep] for name, value in self.items()})

    def append(self, parents: Tensor, **given: Tensor | None) -> "PerGaussian":
        """Rows for new Gaussians appended to every field: each inherits its parent's (`parents
        (M,)` indices), unless `given` has the field's M rows."""
        out = {}
        for name, value in self.items():
            rows = given.get(name)
            out[name] = torch.cat([value, value[parents] if rows is None else rows])
        return PerGaussian(**out)

    def check(self, n: int) -> None:
        """ValueError naming the first field without `n` rows of its shape and kind."""
        for name, value in self.items():
            check_field(name, value, n)

    def state(self) -> dict[str, Tensor]:
        return {name: value.clone() for name, value in self.items()}

    @classmethod
    def from_state(cls, state: dict, n: int) -> "PerGaussian":
        """From a saved model state (`state`'s keys, not all of which are per-Gaussian), checked;
        a field absent from a run saved before it existed gets its fill."""
        out = {}
        for name, f in FIELDS.items():
            value = state.get(name)
            if value is None and f.since_start:
                raise ValueError(f"model state has no field '{name}'")
            if value is None:
                out[name] = f.empty(n)
                continue
            check_field(name, value, n)
            out[name] = value.clone()
        return cls(**out)


def check_rows(fields, n: int, prefix: str = "") -> None:
    """ValueError naming the first of `fields` (name, value) that is not a tensor of `n` rows: a
    mismatch would fail far away, inside an index or the rasteriser."""
    for name, value in fields:
        if not isinstance(value, Tensor) or value.dim() == 0 or len(value) != n:
            got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
            raise ValueError(f"model state field '{prefix}{name}': expected {n} rows (one per Gaussian), got {got}")


def check_field(name: str, value, n: int) -> None:
    f = FIELDS[name]
    check_rows([(name, value)], n)
    if tuple(value.shape[1:]) != f.tail or not f.ok(value):
        raise ValueError(
            f"model state field '{name}': expected {f.expected} of shape "
            f"({', '.join(map(str, (n, *f.tail)))}), got {tuple(value.shape)} {value.dtype}"
        )
