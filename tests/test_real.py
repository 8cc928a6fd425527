"""Real footage: a small fixture derived from the shared BARD-GS `walk` pair (25 blurry + 25
sharp frames at 96x54, with their SfM poses and points; scripts/make_real_fixture.py). A person
walks past a static corridor, filmed by a hand-held blurry camera; the sharp camera is held
out."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kgs_app.bench.real import CROP_PX, dynamic_masks, resolve_clip, sharp_camera_metrics
from kgs_core.data.formats import load_scene
from kgs_core.run import load_run
from kgs_core.train.config import make_config
from kgs_core.train.trainer import train

FIXTURE = Path(__file__).parent / "fixtures" / "walk96"


@pytest.fixture(scope="module")
def walk():
    return load_scene(FIXTURE)


@pytest.fixture(scope="module")
def walk_runs(walk, tmp_path_factory):
    """The full method (settings fitted to the clip) and a static 3DGS, same iterations
    (about 20 s together on two cores)."""
    root = tmp_path_factory.mktemp("walk")
    runs = {}
    for name, ablate in (("full", ()), ("static", ("deform",))):
        cfg = make_config("fast", ablate=ablate, scene=walk, iterations=1000, eval_every=1000, checkpoint_every=10**6)
        train(walk, root / name, cfg, progress=False)
        runs[name] = load_run(root / name)
    return runs


@pytest.mark.slow
def test_full_method_beats_static_3dgs_where_the_person_walks(walk, walk_runs):
    """Inside the dynamic-region mask (where the static 3DGS errs: the walking person), the
    full method is clearly better; on the whole frame it is not worse."""
    masks = dynamic_masks(walk_runs["static"].model, walk)
    share = np.mean([m.mean() for m in masks])
    assert 0.02 < share < 0.5, f"the mask should cover the person, not nothing or everything ({share:.1%})"
    full = sharp_camera_metrics(walk_runs["full"].model, walk, False, masks)
    static = sharp_camera_metrics(walk_runs["static"].model, walk, True, masks)
    # (Measured margins: docs/results.md, "Real footage"; the bound leaves room for seed noise.)
    assert full["psnr_mask"] > static["psnr_mask"] + 1.5, (full, static)
    assert full["psnr"] > static["psnr"] + 0.3, (full, static)
    # τ came from the distribution of K, above the fitted floor, and the decomposition left most of the
    # corridor static (a fixed τ called 84-99 % of the Gaussians dynamic on real footage).
    info = walk_runs["full"].info
    assert info["tau"] > info["config"]["model"]["tau"] and "Otsu" in info["tau_choice"]
    assert info["dynamic_share"] < 0.8


def test_detail_falls_with_blur_and_reads_only_the_mask(walk):
    """`gradient_energy`, which `detail_mask` divides render by sharp frame: a blurred sharp
    frame holds less detail than the frame, more blur less still, and pixels outside the mask
    do not count."""
    from scipy import ndimage

    from kgs_core.evaluate import gradient_energy

    frame = walk.test_frames[len(walk.test_frames) // 2].image().astype(np.float64)
    everywhere = np.ones(frame.shape[:2], bool)
    sharp = gradient_energy(frame, everywhere)
    soft, softer = (gradient_energy(ndimage.gaussian_filter(frame, (s, s, 0)), everywhere) for s in (1.0, 2.0))
    assert sharp > soft > softer > 0
    # A frame flat inside the mask and busy outside it has no detail there.
    busy = np.random.default_rng(0).random(frame.shape)
    left = np.zeros(frame.shape[:2], bool)
    left[:, : frame.shape[1] // 2] = True
    busy[:, : frame.shape[1] // 2 + 1] = 0.5
    assert gradient_energy(busy, left) == 0.0 and gradient_energy(busy, ~left) > 0.01


def test_detail_share_sets_render_and_input_against_the_sharp_target(walk):
    """`DetailShare`: the render's and the blurry input's gradient energy over the target's,
    summed over frames, over the frame and in the mask; an input from a camera of another size
    counts over the frame only."""
    from scipy import ndimage

    from kgs_core.evaluate import DetailShare, gradient_energy

    sharp = walk.test_frames[len(walk.test_frames) // 2].image().astype(np.float64)
    soft = ndimage.gaussian_filter(sharp, (1.5, 1.5, 0))
    everywhere = np.ones(sharp.shape[:2], bool)
    left = np.zeros(sharp.shape[:2], bool)
    left[:, : sharp.shape[1] // 3] = True
    share = DetailShare()
    share.add(sharp, soft, sharp, left)
    share.add(soft, soft, sharp, left)  # a second frame: the sums, not the mean of ratios
    r = share.result()
    assert r["detail"] == pytest.approx(
        (gradient_energy(sharp, everywhere) + gradient_energy(soft, everywhere)) / (2 * gradient_energy(sharp, everywhere))
    )
    assert r["detail_input"] == pytest.approx(gradient_energy(soft, everywhere) / gradient_energy(sharp, everywhere))
    assert r["detail_input_dynamic"] == pytest.approx(gradient_energy(soft, left) / gradient_energy(sharp, left))
    assert 0 < r["detail_input"] < r["detail"] < 1 and r["detail_dynamic"] != r["detail"]
    other = DetailShare()
    other.add(sharp, soft[:-8], sharp, left)  # the input from another camera size
    o = other.result()
    assert o["detail_input_dynamic"] is None and o["detail_input"] < 1 and o["detail_dynamic"] == pytest.approx(1)
    assert DetailShare().result() == dict.fromkeys(r)  # nothing added: no share at all


def test_detail_crop_finds_the_most_detailed_window_outside_the_mask():
    from kgs_core.evaluate import detail_crop

    img = np.full((300, 400, 3), 0.5)
    rng = np.random.default_rng(0)
    img[40:120, 240:320] = rng.random((80, 80, 3))  # busy
    img[200:280, 40:120] = rng.random((80, 80, 3)) * 0.3 + 0.35  # less busy
    y, x = detail_crop(img, 80)
    assert (y, x) == (40, 240)
    busy = np.zeros(img.shape[:2], bool)  # the busy patch and around it: a window may overlap a quarter
    busy[:160, 200:] = True
    assert detail_crop(img, 80, exclude=busy) == (200, 40)
    assert detail_crop(img, 1000) == (0, 0)  # a window larger than the image is the image


@pytest.mark.slow
def test_the_time_offset_scan_finds_held_out_frames_stamped_a_frame_late(walk, walk_runs):
    """Held-out frames whose times are all one frame late are met best earlier, at about what
    their true times give; at their true times a shift gains less."""
    import dataclasses

    from kgs_app.bench.real import best_time_offset

    model = walk_runs["full"].model
    masks = dynamic_masks(walk_runs["static"].model, walk)
    true = sharp_camera_metrics(model, walk, False, masks)["psnr_mask"]
    late = [dataclasses.replace(f, time=min(f.time + walk.dt, 1.0)) if f.split == "test" else f for f in walk.frames]
    stamped_late = dataclasses.replace(walk, frames=late)
    at_late = sharp_camera_metrics(model, stamped_late, False, masks)["psnr_mask"]
    found = best_time_offset(model, stamped_late, masks, at_late)
    # Measured: 17.59 at the late stamps, 19.34 half a frame earlier, 19.27 at the true times
    # (Zen 3); 16.78, 17.65 and 17.26 (Zen 4, AVX-512: the fixture trains to another model
    # there). The scan's gain over the late stamps is what is tested, with room for both.
    assert found["best_offset_frames"] < 0, (found, at_late, true)
    assert found["psnr_mask_best_offset"] > max(at_late + 0.5, true - 0.5), (found, at_late, true)
    gain_at_true_times = best_time_offset(model, walk, masks, true)["psnr_mask_best_offset"] - true
    assert gain_at_true_times < found["psnr_mask_best_offset"] - at_late


def test_settings_follow_the_clip(walk):
    """The fitted settings: τ in this scene's units for the same image motion as on the demo,
    at least one temporal cell per four frames, every choice recorded with its reason;
    explicit values win."""
    from kgs_core.train.fitting import TAU_RMS_PX, scene_pixels_per_unit

    cfg = make_config("fast", scene=walk)
    ppu = scene_pixels_per_unit(walk)
    assert ppu is not None and 50 < ppu < 1000
    assert cfg.model.tau == pytest.approx((TAU_RMS_PX / ppu) ** 2, rel=1e-2)
    assert cfg.model.deform_temporal == max(16, len(walk.train_frames) // 4)
    assert set(cfg.fitted) >= {"model.tau"} and all(isinstance(v, str) for v in cfg.fitted.values())
    mine = make_config("fast", scene=walk, **{"model.tau": 1e-3, "model.deform_temporal": 8})
    assert mine.model.tau == 1e-3 and mine.model.deform_temporal == 8
    assert "model.tau" not in mine.fitted and "model.deform_temporal" not in mine.fitted
    assert make_config("fast").fitted == {}
    # FLoD's first level at the demo's fraction of the image width (0.02 units there; the same
    # 0.02 is 16 px on walk at 320 px), fitted only where there is more than one level.
    from kgs_core.train.fitting import LOD_LAMBDA_WIDTH

    # The paper preset is the paper as written on a video ingest too: five levels (the first
    # one's scale fitted: the paper leaves λ open), τ = 2e-5 fixed, K.R. by eqs. 9-19 on the
    # predicted Σ, none of the additions the fast preset fits to real footage.
    paper = make_config("paper", scene=walk)
    five = paper
    assert paper.lod_levels == 5 and "lod_levels" not in paper.fitted and "lod_lambda" in paper.fitted
    assert paper.model.tau == 2e-5 and not paper.tau_auto and "model.tau" not in paper.fitted
    assert (paper.model.kr_form, paper.model.kr_inputs, paper.model.velocity) == ("paper", "predicted", "paper")
    assert paper.lambda_flow == 0 and paper.spawn_frames == 0 and paper.flow_vote_share == 0
    assert not paper.model.time_opacity and paper.camera_blur == "off" and paper.kr_check_at == 0
    assert paper.reg_static_samples > 0 and paper.noise_until <= paper.decompose_at / paper.iterations
    assert paper.model.deform_temporal == 25 and not paper.decompose_in_place
    assert make_config("paper", scene=walk, lod_levels=1).lod_levels == 1
    width = walk.train_frames[0].camera.width
    assert five.lod_lambda * ppu == pytest.approx(LOD_LAMBDA_WIDTH * width, rel=1e-2) and "lod_lambda" in five.fitted
    assert "lod_lambda" not in cfg.fitted and cfg.lod_lambda == make_config("fast").lod_lambda
    assert make_config("paper", scene=walk, lod_levels=5, lod_lambda=0.05).lod_lambda == 0.05
    # The paper preset keeps to the fast preset's Gaussian budget (the paper's own models end
    # with 33-62k), and a random start fits in it.
    assert paper.densify.max_gaussians == cfg.densify.max_gaussians and paper.init_points <= paper.densify.max_gaussians
    # A video ingest trains with the flow term; a scene that is not one, or an explicit 0, without.
    from dataclasses import replace

    from kgs_core.train.fitting import VIDEO_FLOW_WEIGHT, VIDEO_SPAWN_FRAMES

    assert cfg.lambda_flow == VIDEO_FLOW_WEIGHT > 0 and "lambda_flow" in cfg.fitted
    assert cfg.spawn_frames == VIDEO_SPAWN_FRAMES > 0 and "spawn_frames" in cfg.fitted
    off = make_config("fast", scene=walk, lambda_flow=0.0, spawn_frames=0)
    assert off.lambda_flow == 0.0 and off.spawn_frames == 0
    no_ingest = replace(walk, extras={k: v for k, v in walk.extras.items() if k != "ingest"})
    assert make_config("fast", scene=no_ingest).lambda_flow == 0.0
    assert make_config("fast", scene=no_ingest).spawn_frames == 0
    assert make_config("paper", scene=no_ingest).lod_levels == 5
    # ... and with one-way re-decompositions (a static Gaussian stays static); elsewhere both ways.
    assert cfg.redecompose_to_dynamic is False and "redecompose_to_dynamic" in cfg.fitted
    assert make_config("fast", scene=no_ingest).redecompose_to_dynamic is True
    assert make_config("fast", scene=walk, redecompose_to_dynamic=True).redecompose_to_dynamic is True
    # ... and with an opacity that varies in time for the dynamic Gaussians.
    assert cfg.model.time_opacity is True and "model.time_opacity" in cfg.fitted
    assert make_config("fast", scene=no_ingest).model.time_opacity is False
    assert make_config("fast", scene=walk, **{"model.time_opacity": False}).model.time_opacity is False
    # ... and with decompositions that read DIS's flow down to full resolution (small, fast objects).
    assert cfg.flow_vote_method == "dis_full" and "flow_vote_method" in cfg.fitted
    assert cfg.flow_method == "dis" and make_config("fast", scene=no_ingest).flow_vote_method == "dis"
    assert make_config("fast", scene=walk, flow_vote_method="dis").flow_vote_method == "dis"


def test_equal_time_mean_covers_seeds_that_needed_no_retraining():
    """Seed 1's baseline ran within the budget, so it was not re-trained: its own run stands in
    the "same time" row's mean, which then averages all three seeds."""
    from kgs_app.bench.real import fill_equal_time, mean_over_seeds

    per_seed = {
        "base": {0: {"psnr": 20.0}, 1: {"psnr": 21.0}, 2: {"psnr": 22.0}},
        "base, same time": {0: {"psnr": 19.0}, 2: {"psnr": 23.0}},
    }
    fill_equal_time(per_seed)
    assert per_seed["base, same time"][1] == {"psnr": 21.0}
    assert mean_over_seeds(per_seed["base, same time"])["psnr"] == pytest.approx(21.0)
    assert mean_over_seeds(per_seed["base"])["psnr"] == pytest.approx(21.0)


def test_equal_time_retimes_a_configuration_that_trained_a_few_percent_shorter_or_longer():
    """Only timing noise keeps the first round's result: a baseline 7 % shorter or 5 % longer
    than the full method is trained again at the count its measured rate gives for the full
    method's time; one 1 % apart is not."""
    from types import SimpleNamespace

    from kgs_app.bench.equal_time import equal_time

    rate = {"full": 1.0, "short": 0.93, "long": 1.05, "near": 0.99}  # seconds per iteration

    def trainer_for(name, n, suffix):
        return SimpleNamespace(name=name, n=n, train_seconds=0.0)

    def train_all(trainers):
        for tr in trainers:
            tr.train_seconds = rate[tr.name] * tr.n

    first, second = equal_time(list(rate), trainer_for, 1000, train_all=train_all)
    assert [t.name for t in first] == list(rate) and not any(t.retimed for t in first)
    assert {t.name: t.iterations for t in second} == {"short": round(1000 / 0.93), "long": round(1000 / 1.05)}
    assert all(t.retimed and t.seconds == pytest.approx(1000.0, abs=1.1) for t in second)  # to one iteration


def test_bench_real_finds_clip_pairs(tmp_path):
    (tmp_path / "x_blur.mp4").write_bytes(b"")
    (tmp_path / "x_sharp.mp4").write_bytes(b"")
    assert resolve_clip("x", tmp_path) == ("x", tmp_path / "x_blur.mp4", tmp_path / "x_sharp.mp4")
    assert resolve_clip(str(tmp_path / "x_blur.mp4"), Path("."))[0] == "x"
    with pytest.raises(SystemExit, match="y_blur.mp4 not found"):
        resolve_clip("y", tmp_path)
    with pytest.raises(SystemExit, match="NAME_blur"):
        resolve_clip(str(tmp_path / "x_sharp.mp4"), tmp_path)


def test_exposure_override_and_the_kr_note(walk, tmp_path):
    """`--exposure` replaces the scene's, and a run whose exposure is 0 says that K.R. does
    nothing."""
    cfg = make_config("fast", scene=walk, iterations=2, exposure=0.0, eval_every=10, checkpoint_every=10)
    info = train(walk, tmp_path / "r", cfg, progress=False)
    assert info["exposure"] == 0.0 and "K.R. has no blur to model" in info["kr_note"]
    cfg = make_config("fast", scene=walk, iterations=2, eval_every=10, checkpoint_every=10)
    info = train(walk, tmp_path / "s", cfg, progress=False)
    assert info["exposure"] == walk.exposure == 0.5 and "no blur to model" not in info.get("kr_note", "")
    with pytest.raises(ValueError, match="exposure must be in"):
        make_config("fast", exposure=1.5)


def test_bench_real_end_to_end_on_a_cached_clip(tmp_path):
    """`kgs-app bench real` on the fixture (its ingest cached under --out): every configuration
    trained, scored on the frame and in the mask, pictures and plot written."""
    import json
    import shutil

    from kgs_app.bench.real import main

    data = tmp_path / "data"
    data.mkdir()
    for cam in ("blur", "sharp"):
        (data / f"walk_{cam}.mp4").write_bytes(b"")  # never decoded: the scene is cached
    out = tmp_path / "out"
    shutil.copytree(FIXTURE, out / "scenes" / "walk96")
    assert (
        main(
            [
                "walk",
                "--data",
                str(data),
                "--size",
                "96",
                "--iterations",
                "40",
                "--configs",
                "full,decompose,decompose@lambda_flow=0",
                "--seeds",
                "0,1",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    results = json.loads((out / "results.json").read_text())["walk"]
    # a configuration with an override gets rows of its own, not its base's
    assert {"full", "no decomposition, D3DGS-like", "no decomposition, D3DGS-like @lambda_flow=0", "static 3DGS"} <= set(results)
    assert (
        results["no decomposition, D3DGS-like"]["seeds"]["0"]["run"]
        != results["no decomposition, D3DGS-like @lambda_flow=0"]["seeds"]["0"]["run"]
    )
    for row in results.values():
        assert 5 < row["psnr"] < 50 and row["iterations"] >= 40
        # the row is the mean of each seed's, and the seeds trained apart
        seeds = row["seeds"]
        assert set(seeds) == {"0", "1"} and seeds["0"]["run"] != seeds["1"]["run"]
        assert row["psnr"] == pytest.approx((seeds["0"]["psnr"] + seeds["1"]["psnr"]) / 2)
    assert results["full"]["seeds"]["0"]["psnr"] != results["full"]["seeds"]["1"]["psnr"]
    table = (out / "results.md").read_text()
    assert "PSNR in mask" in table and "detail in mask (input)" in table and "| **full** | mean |" in table
    assert all(0 < row["detail_mask"] < 3 and 0 < row["detail"] < 3 and 0 < row["detail_input"] < 3 for row in results.values())
    assert (out / "views_walk.png").stat().st_size > 1000 and (out / "psnr_vs_time_walk.png").is_file()
    from PIL import Image

    crops = Image.open(out / "crops_walk.png")  # two rows of full-size crops, one column per picture
    assert crops.height == 2 * min(CROP_PX, 54) and crops.width == 5 * min(CROP_PX, 54)


def test_the_viewer_is_told_what_blur_a_run_learned():
    """`learned_blur`: no exposure, K.R. ablated, K.R. turned off by the mid-run check, K.R.
    measured as doing nothing, and K.R. acting each read from run.json; the camera's own blur
    from the configuration."""
    from kgs_core.evaluate import KR_MIN_GAIN_DB
    from kgs_core.run import learned_blur

    cfg = {"camera_blur": "off", "model": {"kinematic": True}, "ablate": []}
    base = {"exposure": 0.5, "config": cfg}
    assert learned_blur({**base, "exposure": 0.0}) == {
        "objects": False,
        "camera": "off",
        "note": "trained at exposure 0: no blur was modelled",
    }
    assert not learned_blur({**base, "config": {**cfg, "ablate": ["kr"]}})["objects"]
    off = learned_blur({**base, "kr_check": {"iteration": 600, "kept": False, "changed_share": 0.001, "gain_db": 0.0}})
    assert not off["objects"] and "turned off at iteration 600" in off["note"] and "0.1%" in off["note"]
    weak = learned_blur({**base, "kr_effect": {"changed_share": 0.02, "gain_db": KR_MIN_GAIN_DB / 2}})
    assert not weak["objects"] and weak["note"].startswith("exposure 0.50: next to no learned blur")
    acts = learned_blur(
        {**base, "config": {**cfg, "camera_blur": "learned"}, "kr_effect": {"changed_share": 0.05, "gain_db": 2 * KR_MIN_GAIN_DB}}
    )
    assert acts["objects"] and acts["camera"] == "learned" and "5.0% of the training pixels" in acts["note"]
    assert "did not keep it" in acts["note"] and "not modelled" in weak["note"] and "camera_motion" not in acts
    # A run that kept its learned shake hands it to the viewer, whatever K.R. did.
    records = [{"t": 0.0, "w": [0.0, 0.1, 0.0], "b": [0.2, 0.0, 0.0]}]
    learned = {**base, "config": {**cfg, "camera_blur": "learned"}, "camera_motion": records}
    kept = learned_blur({**learned, "kr_effect": {"changed_share": 0.02, "gain_db": 0.0}})
    assert kept["camera_motion"] == records and kept["note"].startswith("exposure 0.50: shows the camera's own shake (learned)")
    assert learned_blur({**base, "camera_motion": records}).get("camera_motion") is None  # camera_blur off: nothing to show


def test_the_camera_s_own_streak_is_measured_and_turns_its_blur_on(walk):
    """`camera_blur_px`: cameras that slide sideways by D a frame at depth z draw streaks of
    f D / z px a frame interval, times the exposure (median over points); a still camera none.
    A scene whose streak reaches CAMERA_BLUR_MIN_PX trains with the camera's blur learned, a
    video ingest or not (a synthetic scene's shaky camera), unless it is set by hand or the K.R.
    form cannot carry it; a shorter streak leaves it off."""
    import dataclasses

    from kgs_core.train.fitting import CAMERA_BLUR_MIN_PX
    from kgs_core.train.scene_measures import camera_blur_px

    frames = sorted(walk.train_frames, key=lambda f: f.time)
    base = frames[0].camera
    step = 0.01

    def moved(i, f):
        vm = base.viewmat.copy()
        vm[0, 3] += i * step
        return dataclasses.replace(f, camera=dataclasses.replace(f.camera, viewmat=vm))

    sliding = dataclasses.replace(walk, frames=[moved(i, f) for i, f in enumerate(frames)] + walk.test_frames)
    z = walk.points @ base.viewmat[2, :3] + base.viewmat[2, 3]
    expected = float(np.median(base.K[0, 0] * step / z[z > 1e-6]))
    # (a random sample of 2,000 points: the median agrees to a percent)
    assert camera_blur_px(sliding, exposure=1.0) == pytest.approx(expected, rel=0.03)
    assert camera_blur_px(sliding, exposure=0.5) == pytest.approx(0.5 * camera_blur_px(sliding, exposure=1.0))
    still = dataclasses.replace(walk, frames=[moved(0, f) for f in frames] + walk.test_frames)
    assert camera_blur_px(still) == 0.0
    streak = camera_blur_px(walk)
    assert streak >= CAMERA_BLUR_MIN_PX  # the fixture's hand-held camera
    assert make_config("fast", scene=walk).camera_blur == "learned"
    assert f"{streak:.1f} px streak" in make_config("fast", scene=walk).fitted["camera_blur"]
    assert make_config("fast", scene=walk, camera_blur="off").camera_blur == "off"
    assert make_config("fast", scene=walk, **{"model.kr_form": "paper"}).camera_blur == "off"
    assert make_config("fast", scene=walk, ablate=("decompose",)).camera_blur == "off"
    assert make_config("fast", scene=still).camera_blur == "off"
    not_video = dataclasses.replace(sliding, extras={k: v for k, v in walk.extras.items() if k != "ingest"})
    assert "ingest" in walk.extras and make_config("fast", scene=not_video).camera_blur == "learned"
    threshold_exposure = CAMERA_BLUR_MIN_PX / camera_blur_px(sliding, exposure=1.0)  # the streak at the threshold
    assert make_config("fast", scene=not_video, exposure=0.9 * threshold_exposure).camera_blur == "off"
    assert make_config("fast", scene=not_video, exposure=1.1 * threshold_exposure).camera_blur == "learned"


def test_a_video_ingest_starts_from_every_sfm_point_up_to_the_gaussian_budget(walk):
    """fit_to_scene: a video ingest with more SfM points than the preset's random subset starts
    from all of them (up to the Gaussian budget), with its reason; a synthetic scene keeps the
    subset, and an explicit value stands."""
    import dataclasses

    preset = make_config("fast")
    rng = np.random.default_rng(0)

    def with_points(n):
        pts = walk.points[rng.integers(0, len(walk.points), n)] + rng.normal(0, 1e-3, (n, 3))
        return dataclasses.replace(walk, points=pts, point_colors=np.full((n, 3), 0.5))

    assert len(walk.points) < preset.init_points
    assert make_config("fast", scene=walk).init_points == preset.init_points
    many = with_points(preset.init_points + 1500)
    cfg = make_config("fast", scene=many)
    assert cfg.init_points == len(many.points) and f"every SfM point ({len(many.points)})" in cfg.fitted["init_points"]
    too_many = with_points(cfg.densify.max_gaussians + 100)
    assert make_config("fast", scene=too_many).init_points == cfg.densify.max_gaussians
    assert make_config("fast", scene=many, init_points=5000).init_points == 5000
    not_video = dataclasses.replace(many, extras={k: v for k, v in walk.extras.items() if k != "ingest"})
    assert make_config("fast", scene=not_video).init_points == preset.init_points


def test_a_detail_share_not_computed_reads_n_a_in_the_table():
    """The input's detail in the mask is not computed where the two cameras' frames differ in
    size (walk): the table says so instead of printing nan."""
    import math

    from kgs_app.bench.real import table_row

    r = dict(psnr=23.0, ssim=0.83, psnr_mask=17.2, ssim_mask=0.67, detail=0.56, detail_input=0.49, detail_mask=0.33)
    r.update(detail_input_mask=math.nan, psnr_mask_best_offset=19.1, best_offset_frames=1, dynamic_share=0.5)
    row = table_row("full", "1", {**r, "gaussians": 1000, "iterations": 3000, "seconds": 214})
    assert "| 0.33 (n/a) |" in row and "nan" not in row and "| 0.56 (0.49) |" in row
