"""A training that fits a time budget (`kgs-app train --time-budget 10m`).

The budget is turned into settings before training, on this machine: a short pilot times real
training steps of the configuration on the scene at two Gaussian counts, a line through the two
gives a step's cost for any count, and the count's path over the run (densification grows it to
the budget between its start and stop) gives the run's time for an iteration count. The
iterations (and, when they would fall below half the preset's, the Gaussian budget) are the
largest that fit; never more than the preset's own, which is what it was tuned to need. The
choice and its reason go into `TrainConfig.fitted`, so run.json says what was picked and why.

The pilot's steps are the warm-up's, in which every Gaussian deforms; after the first
decomposition the static ones skip the field and a step costs less. So the plan is revised
from the run's own steps after that decomposition, after each change of image size and once
more before densification stops (`budget_check_starts`, `refit_gaussian_budget`): the
Gaussian budget grows into the time the pilot overestimated (up to the preset's), or shrinks
when the run is slower than planned. The pilot's cost travels in `TrainConfig.budget_pilot`.
"""

from __future__ import annotations

import math
import re
import statistics
import tempfile
import time
from dataclasses import dataclass, replace

import torch

from .image_levels import divisor_changes, image_divisor

# Steps timed at each Gaussian count of the pilot (after one untimed step); the median counts.
PILOT_STEPS = 7
# Training frames the pilot uses (its flows are computed for these only).
PILOT_FRAMES = 4
# The fewest iterations a budget may leave; a smaller budget is refused.
MIN_ITERATIONS = 200
# Below this share of the preset's iterations a budget also lowers the Gaussian budget.
MIN_ITERATION_SHARE = 0.5
# Steps whose median revises the Gaussian budget (`refit_gaussian_budget`), at each of
# `budget_check_starts`.
BUDGET_CHECK_STEPS = 30
# What a revision keeps back of the budget: less than the pilot's plan, since it measures the
# run's steps and events.
REVISED_HEADROOM = 0.95
# Steps between the checks of a planned run's pace once densification has stopped (`watch_tail`).
TAIL_RECHECK_STEPS = 200
# How far from the pilot's a revision may take a step's cost (either way): a median caught
# beside another process, or in the thread tuner's trial, must not throw the plan.
RATIO_BOUND = 2.0
# The pilot's steps are the warm-up's (every Gaussian deforms), dearer than the ones after the
# split; the plan is kept this far under the budget for what the pilot does not see (events,
# evaluation, the thread tuner settling).
HEADROOM = 0.9

_UNITS = {"s": 1, "m": 60, "min": 60, "h": 3600}


def parse_duration(text: str | float | int) -> float:
    """Seconds from `600`, `600s`, `10m`, `1.5h` (or a number); ValueError naming the value."""
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        seconds = float(text)
    else:
        m = re.fullmatch(r"\s*(\d+(?:\.\d*)?)\s*(s|m|min|h)?\s*", str(text))
        if not m:
            raise ValueError(f"time_budget takes seconds or a duration such as 90s, 10m, 1.5h, got {text!r}")
        seconds = float(m.group(1)) * _UNITS[m.group(2) or "s"]
    if not seconds > 0 or seconds > 7 * 24 * 3600:
        raise ValueError(f"time_budget must be above 0 and at most a week, got {text!r}")
    return seconds


@dataclass(frozen=True)
class StepCost:
    """Seconds a training step costs on this machine at `n` Gaussians: `fixed + per_gaussian * n`
    (per-pixel work, and per-Gaussian work), from two pilot measurements; `fixed_at` holds the
    fixed part at each image divisor above 1 (coarse-to-fine images, `downscales`), where the
    per-pixel work shrinks and the per-Gaussian work stays."""

    fixed: float
    per_gaussian: float
    fixed_at: tuple[tuple[int, float], ...] = ()

    def at(self, n: float, divisor: int = 1) -> float:
        return dict(self.fixed_at).get(divisor, self.fixed) + self.per_gaussian * n

    def to_dict(self) -> dict:
        return {"fixed": self.fixed, "per_gaussian": self.per_gaussian, "fixed_at": [list(p) for p in self.fixed_at]}

    @classmethod
    def from_dict(cls, d: dict) -> "StepCost":
        return cls(float(d["fixed"]), float(d["per_gaussian"]), tuple((int(k), float(v)) for k, v in d.get("fixed_at", ())))

    def run_seconds(self, cfg, start: int, since: int = 0) -> float:
        """The training time of `cfg`'s steps from iteration `since` (0: the whole run), with
        `start` Gaussians then: the count held until densification starts, grown linearly to
        the budget by its stop (densification usually reaches it sooner: an overestimate),
        then held; each stretch at its image size."""
        n_it, d = cfg.iterations, cfg.densify
        top = max(start, d.max_gaussians)
        grow_from = min(max(d.start, since), n_it)
        grow_to = min(max(d.stop, grow_from), n_it)

        def count(x: float) -> float:
            if x <= grow_from:
                return start
            if x >= grow_to:
                return top
            return start + (top - start) * (x - grow_from) / (grow_to - grow_from)

        # Between these steps the count is linear and the image size fixed, and the cost is
        # linear in the count: each stretch costs its length at its middle's count.
        changes = divisor_changes(n_it, cfg.downscales, cfg.downscale_until)
        cuts = sorted({since, n_it, grow_from, grow_to, *(c for c in changes if since < c < n_it)})
        total = 0.0
        for a, b in zip(cuts, cuts[1:]):
            k = image_divisor(a, n_it, cfg.downscales, cfg.downscale_until)
            total += (b - a) * self.at(count(0.5 * (a + b)), k)
        return total


def pilot_cost(cfg, scene) -> tuple[StepCost, int, int]:
    """Times `PILOT_STEPS` real training steps of `cfg` on `PILOT_FRAMES` of `scene`'s training
    frames at its initial Gaussians and at its Gaussian budget (copies of them), the median
    step of each, and fits `StepCost`; with coarse-to-fine images, also at each smaller size
    at the initial count. Also returns the two counts."""
    from .trainer import Trainer

    pilot_scene = replace(scene, frames=scene.train_frames[:PILOT_FRAMES])
    quiet = replace(cfg, eval_every=10**9, checkpoint_every=10**9, iterations=10**6)
    with tempfile.TemporaryDirectory(prefix="kgs-budget-") as tmp:
        tr = Trainer(pilot_scene, tmp, quiet, progress=False)
        tr.init_model()
        start = len(tr.model)
        divisors = [2**j for j in range(1, cfg.downscales + 1)]
        coarse = {k: _median_step(tr, k) for k in divisors}
        points = []
        for target in (start, max(2 * start, cfg.densify.max_gaussians)):
            _grow(tr, target)
            points.append((len(tr.model), _median_step(tr, 1)))
    (n0, t0_), (n1, t1_) = points
    per = max(0.0, (t1_ - t0_) / max(n1 - n0, 1))
    fixed_at = tuple((k, max(t - per * n0, 0.0)) for k, t in coarse.items())
    return StepCost(fixed=max(t0_ - per * n0, 0.0), per_gaussian=per, fixed_at=fixed_at), n0, n1


def _median_step(trainer, divisor: int) -> float:
    """The median of `PILOT_STEPS` timed steps at image `divisor` (after one untimed step:
    first-call costs)."""
    trainer.divisor_override = divisor
    trainer.train_step(0)
    times = []
    for i in range(PILOT_STEPS):
        t0 = time.perf_counter()
        trainer.train_step(1 + i)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _grow(trainer, target: int) -> None:
    """Appends copies of the Gaussians (each its own parent's) until there are `target`, all
    of them shrunk so that together they cover the screen area the first ones did: as
    densification grows the count, it splits large Gaussians into smaller ones, and a copy
    at full size would time per-pixel work that a trained run's Gaussians do not have."""
    from ..model.gaussians import GaussianParams

    model = trainer.model
    n = len(model)
    if target <= n:
        return
    parents = torch.arange(target - n) % n
    with torch.no_grad():
        new = GaussianParams(**{k: v.detach()[parents].clone() for k, v in vars(model.params).items()})
    model.add_gaussians(new, parents, trainer.opt, trainer.strategy.state)
    with torch.no_grad():
        model.params.log_scales.add_(0.5 * math.log(n / target))


def fit_time_budget(cfg, scene, remake, explicit: set[str]):
    """`cfg` with its iterations (and, for a small budget, its Gaussian budget) chosen to fit
    `cfg.time_budget` seconds on this machine; the plan and its reason in `fitted`.
    `remake(iterations, max_gaussians)` builds the configuration again (the preset lays its
    schedule out for the iteration count). ValueError when `iterations` was also given, or
    when not even `MIN_ITERATIONS` at the initial Gaussian count fit."""
    budget = cfg.time_budget
    if "iterations" in explicit:
        raise ValueError("give iterations or time_budget, not both (the budget picks the iterations)")
    cost, start, top = pilot_cost(cfg, scene)
    target = HEADROOM * budget
    preset_it, preset_g = cfg.iterations, cfg.densify.max_gaussians
    full = cost.run_seconds(cfg, start)
    pilot = f"a pilot of {1000 * cost.at(start):.0f} ms a step at {start:,} Gaussians and {1000 * cost.at(top):.0f} ms at {top:,}"
    # (A budget fitted to the scene has its reason there already: the plan follows it.)
    why = f"{cfg.fitted['time_budget']}; " if "time_budget" in cfg.fitted else f"{budget:.0f} s: "
    # What the run's own steps revise after the first decomposition; a Gaussian budget given by
    # hand is kept as given.
    pilot_record = (
        {} if "densify.max_gaussians" in explicit else {"cost": cost.to_dict(), "most_gaussians": preset_g, "most_iterations": preset_it}
    )
    if full <= target:
        fits_all = f"the preset's {preset_it} iterations up to {preset_g:,} Gaussians fit"
        cfg.fitted["time_budget"] = f"{why}{fits_all} ({full:.0f} s planned from {pilot})"
        cfg.budget_pilot = pilot_record
        return cfg
    fits = lambda n, g: cost.run_seconds(remake(n, g), start) <= target  # noqa: E731
    g = preset_g
    n = _largest(lambda k: fits(k, g), MIN_ITERATIONS, preset_it)
    if n < MIN_ITERATION_SHARE * preset_it and "densify.max_gaussians" not in explicit:
        # Fewer Gaussians before fewer iterations: a short run cannot use a large budget anyway.
        n = max(MIN_ITERATIONS, int(MIN_ITERATION_SHARE * preset_it))
        g = _largest(lambda gg: fits(n, gg), start, preset_g)
        if not fits(n, g):  # not even at the initial count: fewer iterations still
            n = _largest(lambda k: fits(k, g), MIN_ITERATIONS, n)
    if not fits(n, g):
        raise ValueError(
            f"time_budget of {budget:.0f} s is too short for this scene on this machine: "
            f"{MIN_ITERATIONS} iterations would take about "
            f"{cost.run_seconds(remake(MIN_ITERATIONS, g), start) / HEADROOM:.0f} s ({pilot})"
        )
    out = remake(n, g)
    out.time_budget = budget
    out.budget_pilot = pilot_record
    planned = cost.run_seconds(out, start)
    fewer = f", a Gaussian budget of {g:,} of its {preset_g:,}" if g != preset_g else ""
    out.fitted["time_budget"] = (
        f"{why}{n} of the preset's {preset_it} iterations{fewer} ({planned:.0f} s "
        f"planned, the preset's would take {full:.0f} s; from {pilot})"
    )
    return out


def read_budget_pilot(record: dict) -> tuple[StepCost, int]:
    """`TrainConfig.budget_pilot`'s cost and most Gaussians; ValueError naming the field when
    it is not what `fit_time_budget` writes (finite numbers, none below 0; whole counts;
    `most_iterations` is absent from runs planned before it)."""
    try:
        cost, most = StepCost.from_dict(record["cost"]), record["most_gaussians"]
        numbers = [cost.fixed, cost.per_gaussian, *(v for _, v in cost.fixed_at)]
        counts = [most, record.get("most_iterations", 1)]
        ok = all(math.isfinite(v) and v >= 0 for v in numbers) and all(isinstance(k, int) and k >= 1 for k in counts)
    except (KeyError, TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(
            "budget_pilot must be empty or {'cost': {'fixed', 'per_gaussian', 'fixed_at'}, 'most_gaussians', 'most_iterations'} "
            f"as a time budget's pilot writes it (numbers >= 0, whole counts >= 1), got {record!r}"
        )
    return cost, most


def tail_iterations(cfg, it: int, step_seconds: float, seconds_left: float) -> int:
    """The iteration count for a planned run whose densification has stopped (its Gaussian
    count is final), from its own steps: `it` plus as many steps of `step_seconds` as fit
    `seconds_left`, never more than the preset's (`most_iterations` of `cfg.budget_pilot`; the
    planned count for a run planned before it was recorded) and at least one more step.

    Densification adds what its gradient threshold selects, not what the budget allows, so a
    plan that left room for more Gaussians than densification made ends early; the time it
    leaves buys iterations, which is what deblurring needs (docs/method.md, "A time budget").
    The other way, a run whose steps came out dearer than planned (spawned Gaussians come on
    top of the Gaussian budget) ends sooner, so that the budget holds."""
    most = cfg.budget_pilot.get("most_iterations", cfg.iterations)
    affordable = it + int(max(seconds_left, 0.0) / max(step_seconds, 1e-9))
    return max(it + 1, min(affordable, max(most, cfg.iterations)))


def read_tail(saved, train_seconds: float) -> tuple[list[tuple[int, float, float]], int] | None:
    """`Trainer.tail` from a checkpoint's record: None, `(knots, planned total)`, or an older
    checkpoint's `(step, planned total)`, read as one knot where the step and the schedule
    agreed (its time the checkpoint's: the first pace check after the resume reads low)."""
    if not saved:
        return None
    first, before = saved
    if isinstance(first, (int, float)):
        return [(int(first), float(first), float(train_seconds))], int(before)
    return [(int(a), float(p), float(s)) for a, p, s in first], int(before)


def refit_gaussian_budget(cfg, it: int, count: int, step_seconds: float, divisor: int, seconds_left: float) -> tuple[int, StepCost]:
    """The Gaussian budget for the rest of a planned run (`cfg.budget_pilot`), from its own
    steps: the pilot's cost scaled by `step_seconds` (a median step at `count` Gaussians and
    image `divisor`, just before iteration `it`) over the pilot's own for that step, the ratio
    held within a factor RATIO_BOUND; the budget is the largest in [count, the preset's] whose
    remaining steps fit `seconds_left`, and `count` (no more densification) when none does.
    Also returns the revised cost.

    A scale, not a shift: the steps after the decomposition are cheaper in both parts, the
    per-Gaussian one (static Gaussians skip the field) and the per-pixel one (trained
    Gaussians are smaller than the pilot's), and a shift would carry a step measured at a
    smaller image size to full size as an absolute saving. Each image size's first steps
    revise the plan again."""
    pilot, most = read_budget_pilot(cfg.budget_pilot)
    expected = pilot.at(count, divisor)
    ratio = min(max(step_seconds / max(expected, 1e-12), 1 / RATIO_BOUND), RATIO_BOUND)
    cost = StepCost(pilot.fixed * ratio, pilot.per_gaussian * ratio, tuple((k, v * ratio) for k, v in pilot.fixed_at))
    most = max(count, most)

    def fits(g: int) -> bool:
        planned = replace(cfg, densify=replace(cfg.densify, max_gaussians=g))
        return cost.run_seconds(planned, count, since=it) <= seconds_left

    return _largest(fits, count, most), cost


def budget_check_starts(cfg) -> list[int]:
    """The iterations after which `BUDGET_CHECK_STEPS` steps revise a planned run's Gaussian
    budget: the first decomposition, each change of image size while densification runs, and
    once more halfway from the last of them to densification's stop, where there is room for
    its steps and growth after them: the first steps at a new size can run dearer than the ones
    that follow, and a plan read from them alone leaves the budget's time unused."""
    stop = cfg.densify.stop
    changes = divisor_changes(cfg.iterations, cfg.downscales, cfg.downscale_until)
    starts = sorted(s for s in {cfg.decompose_at, *changes} if cfg.decompose_at <= s < stop)
    if starts:
        late = (starts[-1] + stop) // 2
        if min(late - starts[-1], stop - late) > BUDGET_CHECK_STEPS:
            starts.append(late)
    return starts


def tail_check_start(cfg) -> int | None:
    """The iteration after which `BUDGET_CHECK_STEPS` steps set a planned run's iteration count
    (`tail_iterations`): densification's stop, where the Gaussian count is final; None when
    the run ends too soon after it (or densification never stops within it)."""
    stop = cfg.densify.stop
    return stop if stop + 2 * BUDGET_CHECK_STEPS < cfg.iterations else None


def _largest(fits, low: int, high: int) -> int:
    """The largest whole number in [low, high] for which `fits` holds (it holds for all below
    one that does), or `low` when none does."""
    if fits(high):
        return high
    lo, hi = low, high - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if fits(mid):
            lo = mid
        else:
            hi = mid - 1
    return lo
