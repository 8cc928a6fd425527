"""`--time-budget`: a training planned to fit a time on this machine (train/budget.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from kgs_core.data.formats import load_scene
from kgs_core.train import budget
from kgs_core.train.budget import HEADROOM, MIN_ITERATIONS, StepCost, parse_duration
from kgs_core.train.config import make_config

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
