"""`--time-budget`: a training planned to fit a time on this machine (train/budget.py)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
import torch

from kgs_core.data.formats import load_scene
from kgs_core.train import budget
from kgs_core.train.budget import BUDGET_CHECK_STEPS, HEADROOM, MIN_ITERATIONS, StepCost, parse_duration
from kgs_core.train.config import TrainConfig, make_config
from kgs_core.train.trainer import Trainer

FIXTURE = Path(__file__).parent / "fixtures" / "walk96"


@pytest.fixture(scope="module")
def walk():
    return load_scene(FIXTURE)


def test_durations_read_as_seconds_and_nonsense_is_refused():
    assert parse_duration("10m") == 600 and parse_duration("90s") == 90 and parse_duration("1.5h") == 5400
    assert parse_duration("600") == 600 and parse_duration(45) == 45 and parse_duration(" 2 min ") == 120
    for bad in ("ten", "0", "-5m", "5 weeks", "1e3", "", "8d", 0, float("nan")):
        with pytest.raises(ValueError, match="time_budget"):
            parse_duration(bad)


def test_a_run_s_time_follows_the_gaussian_count_through_densification():
    """The count is held until densification starts, grows linearly to the budget by its stop,
    then is held: the run's time sums the step cost along that path."""
    cfg = make_config("fast", iterations=1000, **{"densify.max_gaussians": 5000})
    d = cfg.densify
    cost = StepCost(fixed=0.01, per_gaussian=1e-6)
    start = 1000
    expected = d.start * cost.at(start) + (d.stop - d.start) * cost.at((start + 5000) / 2) + (1000 - d.stop) * cost.at(5000)
    assert cost.run_seconds(cfg, start) == pytest.approx(expected)
    assert d.start > 0 and d.stop < 1000  # every part of the path is exercised


@pytest.fixture
def known_cost(monkeypatch):
    """The pilot replaced by a known machine: 10 ms a step plus 1 ms per thousand Gaussians."""
    cost = StepCost(fixed=0.010, per_gaussian=1e-6)
    monkeypatch.setattr(budget, "pilot_cost", lambda cfg, scene: (cost, 1000, cfg.densify.max_gaussians))
    return cost


def test_a_budget_picks_the_most_iterations_that_fit(walk, known_cost):
    preset = make_config("fast", scene=walk)
    whole = known_cost.run_seconds(preset, 1000)
    # Room for the preset's schedule: kept as it is, never longer.
    roomy = make_config("fast", scene=walk, time_budget=2 * whole)
    assert roomy.iterations == preset.iterations and roomy.densify.max_gaussians == preset.densify.max_gaussians
    assert "the preset's" in roomy.fitted["time_budget"]
    # Room for three quarters of it: the most iterations that fit, the schedule laid out again.
    tight = make_config("fast", scene=walk, time_budget=0.75 * whole / HEADROOM)
    assert MIN_ITERATION_SHARE_OF(preset) <= tight.iterations < preset.iterations
    assert known_cost.run_seconds(tight, 1000) <= 0.75 * whole + 1e-9
    one_more = make_config("fast", scene=walk, iterations=tight.iterations + 1, plan_budget=False)
    assert known_cost.run_seconds(one_more, 1000) > 0.75 * whole
    assert tight.densify.stop < preset.densify.stop  # the schedule follows the count
    assert f"{tight.iterations} of the preset's {preset.iterations}" in tight.fitted["time_budget"]


def MIN_ITERATION_SHARE_OF(cfg) -> int:
    return int(budget.MIN_ITERATION_SHARE * cfg.iterations)


def test_a_small_budget_lowers_the_gaussian_budget_before_the_iterations(walk, known_cost):
    preset = make_config("fast", scene=walk)
    half = make_config("fast", scene=walk, iterations=MIN_ITERATION_SHARE_OF(preset), plan_budget=False)
    small = 0.6 * known_cost.run_seconds(half, 1000)
    cfg = make_config("fast", scene=walk, time_budget=small / HEADROOM)
    assert cfg.iterations == MIN_ITERATION_SHARE_OF(preset)
    assert 1000 <= cfg.densify.max_gaussians < preset.densify.max_gaussians
    assert known_cost.run_seconds(cfg, 1000) <= small + 1e-9
    assert "Gaussian budget" in cfg.fitted["time_budget"]


def test_an_impossible_budget_or_one_with_iterations_is_refused(walk, known_cost):
    floor = known_cost.run_seconds(
        make_config("fast", scene=walk, iterations=MIN_ITERATIONS, plan_budget=False, **{"densify.max_gaussians": 1000}), 1000
    )
    with pytest.raises(ValueError, match="too short for this scene"):
        make_config("fast", scene=walk, time_budget=0.5 * floor)
    with pytest.raises(ValueError, match="iterations or time_budget"):
        make_config("fast", scene=walk, time_budget=600.0, iterations=100)
    with pytest.raises(ValueError, match="time_budget must be"):
        make_config("fast", time_budget=-1.0)


def test_the_pilot_times_real_steps_at_two_counts(walk):
    """The real pilot on the fixture: the second count is the Gaussian budget, a step there
    costs at least as much per Gaussian, and the plan is recorded with the configuration."""
    cfg = make_config("fast", scene=walk, **{"densify.max_gaussians": 6000})
    cost, start, top = budget.pilot_cost(cfg, walk)
    assert top == 6000 > start > 0 and cost.fixed >= 0 and cost.per_gaussian >= 0 and cost.at(top) > 0
    planned = make_config("fast", scene=walk, time_budget=3600.0)
    assert planned.time_budget == 3600.0 and "planned from a pilot" in planned.fitted["time_budget"]
    assert planned.to_dict()["time_budget"] == 3600.0 and planned.to_dict()["fitted"]["time_budget"]


def test_the_pilot_grows_the_count_as_splits_do_covering_the_same_area(walk, tmp_path):
    """The pilot's larger count is copies of the initial Gaussians, all shrunk so that together
    they cover the screen area the first ones did (sum of squared scales kept): full-size
    copies would time per-pixel work that a trained run's Gaussians, split smaller, do not have."""
    tr = Trainer(walk, tmp_path, make_config("fast", scene=walk), progress=False)
    tr.init_model()
    n = len(tr.model)
    before = tr.model.params.log_scales.detach().clone()
    budget._grow(tr, 4 * n)
    after = tr.model.params.log_scales.detach()
    assert len(tr.model) == 4 * n
    assert (2 * after).exp().sum(0) == pytest.approx((2 * before).exp().sum(0), rel=1e-4)
    assert torch.allclose(after[:n], before - 0.5 * math.log(4))  # each copy as small as its parent


def test_the_command_line_and_the_rest_body_take_a_budget():
    from kgs_app.cli import build_parser
    from kgs_app.cli_args import options_from
    from kgs_backend.routers.runs import TrainRequest
    from kgs_core.job_options import TrainOptions

    ap = build_parser()
    args = ap.parse_args(["train", "scene", "--out", "o", "--time-budget", "10m"])
    assert options_from(args, TrainOptions).time_budget == 600.0
    with pytest.raises(ValueError, match="time_budget"):
        options_from(ap.parse_args(["train", "scene", "--out", "o", "--time-budget", "soon"]), TrainOptions)
    assert TrainRequest(scene_id="x", time_budget=600).time_budget == 600
    assert TrainRequest(scene_id="x", time_budget="10m").time_budget == 600  # the same reading as the command line
    with pytest.raises(ValueError):
        TrainRequest(scene_id="x", time_budget=10**9)


def test_the_rest_of_a_run_costs_its_steps_from_where_it_is():
    """`since`: only the steps from there count, the count growing from where it is then to the
    budget by densification's stop."""
    cfg = make_config("fast", iterations=1000, **{"densify.max_gaussians": 5000})
    d, cost = cfg.densify, StepCost(fixed=0.01, per_gaussian=1e-6)
    since, now = (d.start + d.stop) // 2, 2000
    expected = (d.stop - since) * cost.at((now + 5000) / 2) + (1000 - d.stop) * cost.at(5000)
    assert cost.run_seconds(cfg, now, since=since) == pytest.approx(expected)
    assert cost.run_seconds(cfg, 5000, since=d.stop) == pytest.approx((1000 - d.stop) * cost.at(5000))
    assert StepCost.from_dict(cost.to_dict()) == cost


def _short_run(walk, iterations: int, densify_every: int, densify_stop: int, **over):
    """The fast preset cut to a run of `iterations` on the fixture: decomposed at 20, densified
    from 10 to `densify_stop` up to 2,000 Gaussians, checkpointed and evaluated twice."""
    return make_config(
        "fast",
        scene=walk,
        iterations=iterations,
        plan_budget=False,
        decompose_at=20,
        checkpoint_every=iterations // 2,
        eval_every=iterations // 2,
        **{"densify.max_gaussians": 2000, "densify.start": 10, "densify.every": densify_every, "densify.stop": densify_stop},
        **over,
    )


def _planned(cfg, most: int, cost: StepCost, budget_s: float):
    return dataclasses.replace(cfg, time_budget=budget_s, budget_pilot={"cost": cost.to_dict(), "most_gaussians": most})


def test_the_run_s_own_steps_revise_the_gaussian_budget():
    """Steps cheaper than the pilot's (the static Gaussians skip the field after the
    decomposition) scale both parts of its cost down and raise the budget to the most whose
    remainder fits the time left, up to the preset's; dearer ones lower it, never below the
    count already there."""
    cfg = make_config("fast", iterations=1000, **{"densify.max_gaussians": 4000})
    pilot = StepCost(fixed=0.01, per_gaussian=2e-6)
    it, n = 300, 3000
    plan = _planned(cfg, 20_000, pilot, 600.0)
    left = pilot.run_seconds(cfg, n, since=it)  # what the plan left for the rest, at the pilot's cost
    cheaper, cost = budget.refit_gaussian_budget(plan, it, n, step_seconds=0.75 * pilot.at(n), divisor=1, seconds_left=left)
    assert cost.per_gaussian == pytest.approx(0.75 * pilot.per_gaussian) and cost.fixed == pytest.approx(0.75 * pilot.fixed)
    assert 4000 < cheaper <= 20_000
    grown = dataclasses.replace(cfg, densify=dataclasses.replace(cfg.densify, max_gaussians=cheaper))
    assert cost.run_seconds(grown, n, since=it) <= left
    one_more = dataclasses.replace(cfg, densify=dataclasses.replace(cfg.densify, max_gaussians=cheaper + 1))
    assert cheaper == 20_000 or cost.run_seconds(one_more, n, since=it) > left
    dearer, _ = budget.refit_gaussian_budget(plan, it, n, step_seconds=1.25 * pilot.at(n), divisor=1, seconds_left=left)
    assert n <= dearer < 4000
    none_left, _ = budget.refit_gaussian_budget(plan, it, n, step_seconds=0.02, divisor=1, seconds_left=-1.0)
    assert none_left == n
    # A median far off the pilot's (a step caught beside another process) counts as RATIO_BOUND
    # times the pilot's step at most.
    _, wild = budget.refit_gaussian_budget(plan, it, n, step_seconds=100 * pilot.at(n), divisor=1, seconds_left=left)
    assert wild.at(n) == pytest.approx(budget.RATIO_BOUND * pilot.at(n))
    # What the steps at half size measured carries to full size: the whole step scales.
    coarse = StepCost(fixed=0.01, per_gaussian=2e-6, fixed_at=((2, 0.004),))
    plan = _planned(cfg, 20_000, coarse, 600.0)
    _, scaled = budget.refit_gaussian_budget(plan, it, n, step_seconds=0.5 * coarse.at(n, 2), divisor=2, seconds_left=left)
    assert scaled.at(n, 2) == pytest.approx(0.5 * coarse.at(n, 2)) and scaled.at(n) == pytest.approx(0.5 * coarse.at(n))


def test_a_plan_records_its_pilot_unless_the_gaussian_budget_was_given(walk, known_cost):
    preset = make_config("fast", scene=walk)
    planned = make_config("fast", scene=walk, time_budget=3600.0)
    assert planned.budget_pilot == {
        "cost": known_cost.to_dict(),
        "most_gaussians": preset.densify.max_gaussians,
        "most_iterations": preset.iterations,
    }
    given = make_config("fast", scene=walk, time_budget=3600.0, **{"densify.max_gaussians": 2000})
    assert given.budget_pilot == {} and given.densify.max_gaussians == 2000
    assert TrainConfig.from_dict(planned.to_dict()).budget_pilot == planned.budget_pilot


def test_the_budget_is_revised_again_before_densification_stops():
    """The revisions come after the first decomposition, after each change of image size, and
    once more halfway from the last of them to densification's stop, where the steps have
    settled at the final size and densification can still grow into time left unused; that
    last one only where its steps and some growth after them fit before the stop."""
    cfg = dataclasses.replace(make_config("fast", iterations=3000), downscales=1, downscale_until=0.5)
    assert (cfg.decompose_at, cfg.densify.stop) == (600, 2100)
    assert budget.budget_check_starts(cfg) == [600, 1500, 1800]
    assert budget.budget_check_starts(dataclasses.replace(cfg, downscales=0)) == [600, 1350]
    tight = dataclasses.replace(cfg, densify=dataclasses.replace(cfg.densify, stop=1500 + 2 * BUDGET_CHECK_STEPS))
    assert budget.budget_check_starts(tight) == [600, 1500]
    late = dataclasses.replace(cfg, decompose_at=2200)  # decomposed after densification: nothing to revise
    assert budget.budget_check_starts(late) == []


@pytest.mark.parametrize("time_left", ["plenty", "none"])
@pytest.mark.parametrize("size", ["full", "half"])
def test_a_planned_run_revises_its_budget_after_the_decomposition_and_keeps_it(walk, tmp_path, time_left, size):
    """A real training planned with a known pilot: after the steps that follow the first
    decomposition the densification budget becomes the revised one (the preset's when the
    pilot's cost leaves time to spare; the count then when no time is left), recorded in
    run.json and in the checkpoints, from which a resumed run keeps it. Steps at half the image
    size may lower the budget, never raise it."""
    base = _short_run(walk, 90, densify_every=20, densify_stop=80, downscales=0 if size == "full" else 1, downscale_until=0.75)
    # A pilot of 1 s a step, nothing per Gaussian: the measured steps are far cheaper (read as
    # RATIO_BOUND times cheaper, 0.5 s).
    cfg = _planned(base, 9000, StepCost(fixed=1.0, per_gaussian=0.0), 1e4 if time_left == "plenty" else 1e-3)
    tr = Trainer(walk, tmp_path / "run", cfg, progress=False)
    tr.run()
    checks = json.loads((tmp_path / "run" / "run.json").read_text())["budget_checks"]
    assert [c["iteration"] for c in checks] == [20 + BUDGET_CHECK_STEPS]
    check = checks[0]
    assert check["max_gaussians_before"] == 2000 and check["step_ms"] > 0 and check["pilot_step_ms"] == 1000.0
    assert check["divisor"] == (1 if size == "full" else 2)
    n = check["gaussians"]
    assert check["max_gaussians"] == (n if time_left == "none" else 9000 if size == "full" else max(2000, n))
    assert tr.strategy.max_gaussians == check["max_gaussians"]
    resumed = Trainer(walk, tmp_path / "run", cfg, progress=False)
    resumed.restore(sorted((tmp_path / "run" / "checkpoints").glob("ckpt_*.pt"))[-1])
    assert resumed.strategy.max_gaussians == check["max_gaussians"] and resumed.budget_checks == checks


def test_time_left_after_densification_sets_the_iterations_up_to_the_preset_s():
    """Once densification has stopped, the run's own step (events included) over the time left
    sets the iteration count: more than planned where time is left, up to the preset's; fewer
    where it is not, down to one more step; a run planned before the preset's count was
    recorded is not lengthened."""
    cfg = make_config("fast", iterations=3000)
    plan = _planned(cfg, 20_000, StepCost(fixed=0.1, per_gaussian=0.0), 600.0)
    plan.budget_pilot["most_iterations"] = 6000
    assert budget.tail_check_start(plan) == plan.densify.stop
    assert budget.tail_iterations(plan, 2130, step_seconds=0.25, seconds_left=300.0) == 2130 + 1200
    assert budget.tail_iterations(plan, 2130, step_seconds=0.25, seconds_left=1e6) == 6000
    assert budget.tail_iterations(plan, 2130, step_seconds=0.25, seconds_left=10.0) == 2130 + 40
    assert budget.tail_iterations(plan, 2130, step_seconds=0.25, seconds_left=-5.0) == 2131
    older = _planned(cfg, 20_000, StepCost(fixed=0.1, per_gaussian=0.0), 600.0)
    assert budget.tail_iterations(older, 2130, step_seconds=0.25, seconds_left=1e6) == 3000
    assert budget.tail_iterations(older, 2130, step_seconds=0.25, seconds_left=10.0) == 2170
    # No check where the run ends within two windows of densification's stop.
    assert budget.tail_check_start(dataclasses.replace(plan, iterations=plan.densify.stop + 2 * BUDGET_CHECK_STEPS)) is None


def test_a_planned_run_with_time_left_after_densification_runs_longer_on_stretched_schedules(walk, tmp_path):
    """A real training planned with a known pilot whose time is far from spent when
    densification stops: the run goes on to the preset's iteration count, which run.json's
    config and log record, with its learning rates continuous at the change and ending at
    their final values; a checkpoint after the change resumes to the same count and schedules."""
    base = _short_run(walk, 120, densify_every=10, densify_stop=40)
    cfg = _planned(base, 2000, StepCost(fixed=1.0, per_gaussian=0.0), 1e4)
    cfg.budget_pilot["most_iterations"] = 150
    tr = Trainer(walk, tmp_path / "run", cfg, progress=False)
    seen = {}
    for it in tr.iterate():
        seen[it] = next(g["lr"] for g in tr.net_opt.param_groups if g["name"] == "grid")
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    change = [c for c in info["budget_checks"] if "iterations" in c]
    assert [(c["iteration"], c["iterations_before"], c["iterations"]) for c in change] == [(40 + BUDGET_CHECK_STEPS, 120, 150)]
    assert tr.iteration == 150 and info["iteration"] == 150 and info["config"]["iterations"] == 150
    assert tr.log_rows[-1]["iteration"] == 150
    at = 40 + BUDGET_CHECK_STEPS
    # (The learning rate logged after step `it` is the one step `it - 1` used.)
    lr = lambda k: tr.cfg.lr_grid * (tr.cfg.lr_grid_final / tr.cfg.lr_grid) ** (k / 120)  # noqa: E731
    assert seen[at] == pytest.approx(lr(at - 1))
    assert seen[at + 2] == pytest.approx(lr(at + (at + 1 - at) * (120 - at) / (150 - at)))
    assert seen[150] == pytest.approx(lr(at + (149 - at) * (120 - at) / (150 - at)))
    assert all(seen[k + 1] <= seen[k] for k in range(1, 150))
    resumed = Trainer(walk, tmp_path / "run", make_config("fast", scene=walk, iterations=120, plan_budget=False), progress=False)
    resumed.restore(tmp_path / "run" / "checkpoints" / "ckpt_000120.pt")
    assert resumed.cfg.iterations == 150 and resumed.tail == tr.tail and tr.tail[0][0][:2] == (at, at)
    assert resumed.schedule_iteration(135) == tr.schedule_iteration(135)


def test_a_planned_run_out_of_time_after_densification_ends_sooner_on_compressed_schedules(walk, tmp_path):
    """A real training whose budget is spent when densification stops (its steps dearer than
    planned) ends one step after the check, which run.json records, its schedules (time noise,
    learning rates) mapped so that the new end is the planned one."""
    base = _short_run(walk, 120, densify_every=10, densify_stop=40, noise_init_frames=1.0, noise_final_frames=0.0, noise_until=0.9)
    cfg = _planned(base, 2000, StepCost(fixed=1e-3, per_gaussian=0.0), 1e-3)
    cfg.budget_pilot["most_iterations"] = 150
    tr = Trainer(walk, tmp_path / "run", cfg, progress=False)
    seen = {}
    for it in tr.iterate():
        seen[it] = next(g["lr"] for g in tr.net_opt.param_groups if g["name"] == "grid")
    at = 40 + BUDGET_CHECK_STEPS
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    change = [c for c in info["budget_checks"] if "iterations" in c]
    assert [(c["iteration"], c["iterations_before"], c["iterations"]) for c in change] == [(at, 120, at + 1)]
    assert tr.iteration == at + 1 and info["config"]["iterations"] == at + 1
    assert tr.schedule_iteration(at + 1) == (120, 120) and tr.schedule_iteration(at) == (at, 120)
    assert tr.noise.sigma(tr.schedule_iteration(at + 1)[0]) == pytest.approx(0.0)
    assert max(seen) == at + 1


def test_the_schedules_run_through_each_knot_to_the_planned_end():
    """After checks that set a run's length at steps 100 (planned 300 -> 400) and 200 (-> 250),
    the schedules' clock is the step up to the first, linear between the knots, and reaches the
    planned 300 at the run's new end; an older checkpoint's `(step, total)` reads as one knot."""
    from kgs_core.train.events import ScheduleEvents

    ev = ScheduleEvents.__new__(ScheduleEvents)
    ev.cfg = make_config("fast", iterations=250)
    p200 = 100 + 100 * (300 - 100) / (400 - 100)
    ev.tail = ([(100, 100.0, 10.0), (200, p200, 20.0)], 300)
    assert ev.schedule_iteration(50) == (50, 300) and ev.schedule_iteration(100) == (100, 300)
    assert ev.schedule_iteration(150)[0] == pytest.approx(100 + 50 * (p200 - 100) / 100)
    assert ev.schedule_iteration(225)[0] == pytest.approx(p200 + 25 * (300 - p200) / 50)
    assert ev.schedule_iteration(250)[0] == pytest.approx(300)
    assert budget.read_tail([120, 3000], 55.0) == ([(120, 120.0, 55.0)], 3000)
    assert budget.read_tail(None, 1.0) is None


def test_a_planned_run_whose_steps_grow_dearer_after_the_first_check_is_shortened_again(walk, tmp_path, monkeypatch):
    """The pace is checked again every TAIL_RECHECK_STEPS steps once densification has stopped:
    a run whose steps stay cheap keeps the first check's count; one whose steps then cost ten
    times as much (here, a step padded with sleep) ends sooner, recorded in run.json."""
    import time as _time

    from kgs_core.train import budget as budget_module

    monkeypatch.setattr(budget_module, "TAIL_RECHECK_STEPS", 20)
    base = _short_run(walk, 120, densify_every=10, densify_stop=40)
    at = 40 + BUDGET_CHECK_STEPS
    probe = Trainer(walk, tmp_path / "probe", base, progress=False)
    for it in probe.iterate():
        if it == at:
            break
    step = probe.train_seconds / at
    # Time for about 80 more steps at that pace when the first check runs: the run is lengthened.
    cfg = _planned(base, 2000, StepCost(fixed=1e-3, per_gaussian=0.0), (probe.train_seconds + 80 * step) / budget_module.REVISED_HEADROOM)
    cfg.budget_pilot["most_iterations"] = 300
    tr = Trainer(walk, tmp_path / "run", cfg, progress=False)
    real_step = tr.train_step

    def slow_step(it):
        if it >= at + 5:
            _time.sleep(10 * step)
        return real_step(it)

    tr.train_step = slow_step
    for _ in tr.iterate():
        pass
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    changes = [(c["iteration"], c["iterations_before"], c["iterations"]) for c in info["budget_checks"] if "iterations" in c]
    assert len(changes) >= 2 and changes[0][0] == at and changes[0][2] > 120
    assert changes[1][0] == at + 20 and changes[1][2] < changes[0][2]
    assert tr.iteration == info["config"]["iterations"] == changes[-1][2]
    assert tr.schedule_iteration(tr.iteration)[0] == pytest.approx(120)


def test_a_malformed_pilot_record_is_refused_by_name(walk, known_cost):
    """A run.json's config read back (a resumed or copied run) with a pilot record that is not
    what the planner writes fails when the configuration is built, naming the field, not in
    the middle of training."""
    good = make_config("fast", scene=walk, time_budget=3600.0).to_dict()
    for bad in (
        {"cost": {"fixed": -1.0, "per_gaussian": 0.0}, "most_gaussians": 10},
        {"cost": {"fixed": 0.1}},
        {"most_gaussians": 5},
        {"cost": "x", "most_gaussians": 5},
        {"cost": {"fixed": 0.1, "per_gaussian": 0.0}, "most_gaussians": 5, "most_iterations": 0},
        {"cost": {"fixed": 0.1, "per_gaussian": 0.0}, "most_gaussians": 5, "most_iterations": 2.5},
    ):
        with pytest.raises(ValueError, match="budget_pilot"):
            TrainConfig.from_dict({**good, "budget_pilot": bad})
    assert TrainConfig.from_dict(good).budget_pilot == good["budget_pilot"]
