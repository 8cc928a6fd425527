"""The equal-time protocol shared by `bench quality` and `bench real`.

Every configuration is first trained for the same iteration count, all of them stepped in
turn (one step each, `interleave`), so that their times are measured under the same machine
conditions. With `budget="time"`, each configuration whose time differs from the first one's by
more than `RETIME_TOLERANCE` is trained again with its iteration count scaled by that measured cost ratio
(the preset's schedule scales with the count); with `cuts > 1` at that many counts spread over
±5 % of it, since a compressed schedule's end state depends on where it is cut.
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from typing import Callable

import torch

from kgs_core.train.trainer import Trainer

# A configuration whose first-round time is within this fraction of the first one's keeps that
# round's result: the tolerance covers timing noise only, since a looser one let the choice of
# whom to re-time decide results (docs/metrics.md, "equal (wall) time").
RETIME_TOLERANCE = 0.03


def interleave(trainers: list[Trainer]) -> list[dict]:
    """Trains several runs one step each in turn and returns their infos.

    Each trainer's `train_seconds` times only its own steps, so runs stepped together are
    timed under the same machine conditions: on a shared VM whose speed drifts by up to 2x
    over minutes, that is what makes their times comparable (sequential runs are not). The
    global RNG state (torch and Python's `random`, which the trainer seeds and draws from) is
    swapped with each step, so every run is the one it would be on its own."""
    gens = [t.iterate() for t in trainers]
    rng: list = [None] * len(gens)
    live = list(range(len(gens)))
    while live:
        for i in list(live):
            if rng[i] is not None:
                torch.set_rng_state(rng[i][0])
                random.setstate(rng[i][1])
            try:
                next(gens[i])
            except StopIteration:
                live.remove(i)
                continue
            rng[i] = (torch.get_rng_state(), random.getstate())
    return [t.info for t in trainers]


@dataclass
class Trained:
    name: str  # the configuration
    trainer: Trainer  # finished: `.run_dir`, `.info`, `.train_seconds`
    iterations: int
    seconds: float  # its training time: measured (first round) or rate x iterations (re-timed)
    retimed: bool  # trained again at the equal-time count


def equal_time(
    names: list[str],
    trainer_for: Callable[[str, int, str], Trainer],
    iterations: int,
    budget: str = "time",
    cuts: int = 1,
    train_all: Callable[[list[Trainer]], object] = interleave,
) -> tuple[list[Trained], list[Trained]]:
    """Trains `names` (the first one sets the budget) and returns `(first round, re-timed runs)`.
    `trainer_for(name, iterations, folder_suffix)` makes a fresh trainer. A re-timed run's time
    is the first round's rate times its count: a time of its own would be measured under other
    machine conditions than the first configuration's. `train_all` trains a list of trainers:
    stepped in turn here (`interleave`), or as Ray tasks (`kgs_app.cluster.run_trainers`), where
    each configuration's rate is its own task's, on whichever node ran it."""
    first = [trainer_for(name, iterations, "") for name in names]
    train_all(first)
    rate = {name: tr.train_seconds / iterations for name, tr in zip(names, first)}
    done = [Trained(name, tr, iterations, tr.train_seconds, False) for name, tr in zip(names, first)]
    if budget != "time":
        return done, []
    target = first[0].train_seconds
    again = [
        (name, max(50, round(target / rate[name]))) for name in names[1:] if abs(rate[name] * iterations / target - 1) > RETIME_TOLERANCE
    ]
    spread = [0.0] if cuts == 1 else [-0.05 + 0.1 * k / (cuts - 1) for k in range(cuts)]
    runs = [(name, max(50, round(n * (1 + f)))) for name, n in again for f in spread]
    if not runs:
        return done, []
    second = [trainer_for(name, n, f"_equal_time_{n}") for name, n in runs]
    train_all(second)
    return done, [Trained(name, tr, n, rate[name] * n, True) for (name, n), tr in zip(runs, second)]
