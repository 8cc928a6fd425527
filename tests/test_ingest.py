"""Video ingest: SfM on a synthetic textured video recovers the cameras; bad videos fail clearly."""

from __future__ import annotations

import numpy as np
import pytest

from kgs_app.bench.ingest import umeyama
from kgs_core.data.formats import load_scene
from kgs_core.data.ingest import ingest
from kgs_core.data.scene import SceneError
from kgs_core.data.video import decode_video, encode_video


def sfm_of_frames(folder, meta, work, mapper: str, keyframe_step: int):
    """`run_sfm` on a `frame_set` folder's first camera, as ingest calls it."""
    from kgs_core.data import sfm

    return sfm.run_sfm(
        folder / "database.db",
        folder / "images",
        work,
        meta["names_a"],
        [],
        meta["sharpness"],
        mapper,
        keyframe_step=keyframe_step,
        progress=False,
    )


def test_video_round_trip(room_video):
    video, gt = room_video
    frames = decode_video(video, progress=False)
    assert len(frames) == len(gt.train_frames) and frames[0].shape == (160, 160, 3)
    err = np.abs(frames[3].astype(float) / 255 - gt.train_frames[3].image()).mean()
    assert err < 0.03  # lossy H.264, but the same picture


def test_decoding_downscales_on_threads_in_order(room_video, monkeypatch):
    """Frames are downscaled on worker threads while decoding goes on: the result is the frames
    in order, each as one downscale of it would be, with the stride and the cap applied."""
    from kgs_core.data.video import downscale

    video, _ = room_video
    monkeypatch.setenv("KGS_THREADS", "2")
    full = decode_video(video, progress=False)
    got = decode_video(video, every=2, max_frames=5, max_size=80, progress=False)
    want = [downscale(f, 80) for f in full[::2][:5]]
    assert len(got) == 5 and got[0].shape == (80, 80, 3)
    assert all(np.array_equal(a, b) for a, b in zip(got, want))
    assert len(decode_video(video, every=3, max_size=80, progress=False)) == len(full[::3])


def test_sfm_recovers_camera_centres(room_video, tmp_path):
    video, gt = room_video
    report = ingest(video, tmp_path / "scene", max_size=None, exposure=0.0, holdout_every=0, progress=False)
    assert report.mapper == "keyframes" and report.attempts[0]["outcome"] == "ok"
    assert report.lens["probe"]["images"] >= 2 and "lens_probe" in report.attempts[0]["stages"]
    assert report.registered_fraction >= 0.9
    assert report.mean_reprojection_error_px < 1.5
    scene = load_scene(tmp_path / "scene")
    got = {f.id: f.camera.center for f in scene.train_frames}
    ids = sorted(got)
    est = np.stack([got[i] for i in ids])
    ref = np.stack([next(f for f in gt.train_frames if f.id == i).camera.center for i in ids])
    s, R, t = umeyama(est, ref)
    aligned = (s * (R @ est.T)).T + t
    extent = np.linalg.norm(gt.points.max(0) - gt.points.min(0))  # scene bounding-box diagonal
    err = np.linalg.norm(aligned - ref, axis=1).max() / extent
    print(f"camera centre error {err:.3%} of the scene extent, {report.registered}/{report.frames} registered")
    assert err < 0.02, f"camera centre error {err:.3%} of the scene extent"
    assert scene.extras["ingest"]["registered"] == report.registered
    # The clip's rate over the stride: what the viewer reads a frame's time in seconds with.
    assert report.fps == pytest.approx(12 / report.stride) and scene.extras["ingest"]["fps"] == report.fps
    # The rasteriser is pinhole: ingest undistorts, and each frame's pixels match its camera.
    for f in scene.train_frames[:4]:
        assert not np.any(f.camera.distortion)
        assert f.image().shape[:2] == (f.camera.height, f.camera.width)


def test_corrupt_video(tmp_path):
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"\x00\x00\x00\x18ftypmp42" + b"garbage" * 100)
    with pytest.raises(SceneError, match=r"bad\.mp4"):
        decode_video(bad, progress=False)
    with pytest.raises(SceneError, match="not found"):
        decode_video(tmp_path / "missing.mp4", progress=False)


def test_mismatched_frame_counts(room_video, tmp_path):
    video, gt = room_video
    short = encode_video([(f.image() * 255).astype(np.uint8) for f in gt.train_frames[:5]], tmp_path / "short.mp4")
    with pytest.raises(SceneError, match="frame counts differ"):
        ingest(video, tmp_path / "out", eval_video=short, progress=False)
    assert not (tmp_path / "out").exists()


def test_unregistrable_video(tmp_path):
    rng = np.random.default_rng(0)
    flat = [np.full((96, 96, 3), 120, np.uint8) + rng.integers(0, 2, (96, 96, 3), dtype=np.uint8) for _ in range(6)]
    video = encode_video(flat, tmp_path / "flat.mp4")
    with pytest.raises(SceneError, match=r"structure from motion.*flat\.mp4.*--fixed-camera"):
        ingest(video, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def test_auto_mapper_falls_back_to_incremental(room_video, tmp_path, monkeypatch):
    """When the keyframes form no model (here: a keyframe step longer than the clip, kept from
    shrinking, leaves one keyframe), auto tries keyframes twice as dense, then goes on to the
    incremental mapper, and records every attempt."""
    from kgs_core.data import sfm
    from kgs_core.data.frame_cache import frame_set

    monkeypatch.setattr(sfm, "MIN_KEYFRAMES", 0)
    video, _ = room_video
    folder, meta, _ = frame_set(video, None, 1, None, None, tmp_path / "cache", False, tmp_path)
    result = sfm_of_frames(folder, meta, tmp_path / "work", "auto", 64)
    assert result.mapper == "incremental"
    assert [(a["mapper"], a.get("keyframe_step")) for a in result.attempts] == [("keyframes", 64), ("keyframes", 32), ("incremental", None)]
    assert [a["outcome"] for a in result.attempts[:2]] == ["no model", "no model"]
    assert result.attempts[2]["registered_fraction"] >= 0.9
    # A keyframe model that poses too few frames (here: every 4th frame's, made to lose three
    # frames whatever the seed) is mapped once more with another seed, then every 2nd frame is
    # keyframed: the retries, without the incremental mapper.
    real = sfm.map_keyframes

    def short_at_step_4(db, images, out, names_a, names_b, step, *args, **kw):
        rec = real(db, images, out, names_a, names_b, step, *args, **kw)
        if step == 4:
            for frame_id in sorted(rec.reg_frame_ids())[-3:]:
                rec.deregister_frame(frame_id)
        return rec

    monkeypatch.setattr(sfm, "map_keyframes", short_at_step_4)
    result = sfm_of_frames(folder, meta, tmp_path / "work2", "auto", 4)
    steps = [(a["mapper"], a.get("keyframe_step"), a.get("seed")) for a in result.attempts]
    assert steps == [("keyframes", 4, 0), ("keyframes", 4, sfm.KEYFRAME_RETRY_SEED), ("keyframes", 2, 0)], result.attempts
    assert max(a["registered_fraction"] for a in result.attempts[:2]) < 0.95 <= result.attempts[2]["registered_fraction"]
    assert result.mapper == "keyframes"


@pytest.mark.parametrize("second_camera, first_step", [(True, 8), (False, 4)])
def test_long_clips_keyframe_every_8th_frame_only_with_a_second_camera(second_camera, first_step, tmp_path, monkeypatch):
    """From 256 frames per camera auto starts from keyframes every 8th frame when a second camera
    gives each keyframe its same-time twin; one video starts from every 4th, where every 8th fell
    apart in most draws (docs/data.md, "Ingest speed")."""
    from kgs_core.data import sfm

    steps = []

    def no_model(db, images, out, names_a, names_b, step, *args, **kw):
        steps.append(step)
        return None

    monkeypatch.setattr(sfm, "map_keyframes", no_model)
    monkeypatch.setattr(sfm, "map_incremental", lambda *args: None)
    names_a = [f"f{i:05d}_a.png" for i in range(300)]
    names_b = [n.replace("_a.", "_b.") for n in names_a] if second_camera else []
    assert sfm.run_sfm(tmp_path / "database.db", tmp_path, tmp_path / "work", names_a, names_b, {}, "auto", progress=False) is None
    assert steps == [first_step, first_step // 2]
    # A shorter clip starts from every 4th frame either way.
    steps.clear()
    sfm.run_sfm(tmp_path / "database.db", tmp_path, tmp_path / "work", names_a[:200], names_b[:200], {}, "auto", progress=False)
    assert steps[0] == 4


def test_frames_without_a_keyframe_pair_are_posed_in_a_later_pass(room_video, tmp_path, monkeypatch):
    """A frame that shares no verified pair with any keyframe (as a quarter of the frames do
    with keyframes every 8th frame, where sequential matching pairs only frames a power of two
    apart) is posed in a second pass, through its matches to frames the first pass posed. Here
    the keyframes are every 2nd frame (8 of 16: four keyframes formed a model only some of the
    time) and the pairs of frames 3, 7, 11 and 15 with every keyframe are hidden; their pairs
    with frames 1, 5, 9 and 13, which the first pass poses, are not."""
    from kgs_core.data import register, sfm
    from kgs_core.data.frame_cache import frame_set

    monkeypatch.setattr(sfm, "MIN_KEYFRAMES", 0)
    video, _ = room_video
    folder, meta, _ = frame_set(video, None, 1, None, None, tmp_path / "cache", False, tmp_path)
    names = meta["names_a"]
    with sfm._open_db(folder / "database.db") as d:
        index = {im.image_id: names.index(im.name) for im in d.read_all_images()}
    real = register.verified_partners

    def hidden(i, j):
        return index[i] % 4 == 3 and index[j] % 2 == 0

    def without_keyframe_pairs(d):
        return {i: [j for j in js if not (hidden(i, j) or hidden(j, i))] for i, js in real(d).items()}

    monkeypatch.setattr(register, "verified_partners", without_keyframe_pairs)
    stages = {}
    rec = sfm.map_keyframes(folder / "database.db", folder / "images", tmp_path / "work", names, [], 2, progress=False, stages=stages)
    assert rec.num_reg_images() == len(names)
    passes = stages["register_passes"]
    assert len(passes) >= 2 and passes[0] <= 4 and sum(passes) == 8, passes
    rec.update_point_3d_errors()
    assert rec.compute_mean_reprojection_error() < 1.5


def test_auto_mapper_maps_keyframes_that_fell_apart_again_with_another_seed(room_video, tmp_path, monkeypatch):
    """Keyframes that fall apart into fragments (here: seed 0 made to) are mapped once more with
    KEYFRAME_RETRY_SEED before the denser keyframes or the incremental mapper; both attempts are
    recorded with their seeds. An explicit `--mapper keyframes` does not retry."""
    from kgs_core.data import sfm
    from kgs_core.data.frame_cache import frame_set

    real = sfm.map_keyframes
    seeds = []

    def fragile(*args, seed=0, **kw):
        seeds.append(seed)
        if seed == 0:
            raise sfm.KeyframesFellApart("the keyframes fell apart into 5 models, the largest 3 of 8")
        return real(*args, seed=seed, **kw)

    monkeypatch.setattr(sfm, "map_keyframes", fragile)
    video, _ = room_video
    folder, meta, _ = frame_set(video, None, 1, None, None, tmp_path / "cache", False, tmp_path)
    result = sfm_of_frames(folder, meta, tmp_path / "work", "auto", 2)
    assert seeds == [0, sfm.KEYFRAME_RETRY_SEED] and result.mapper == "keyframes"
    assert [(a["keyframe_step"], a["seed"]) for a in result.attempts] == [(2, 0), (2, sfm.KEYFRAME_RETRY_SEED)]
    assert "fell apart" in result.attempts[0]["outcome"] and result.attempts[1]["outcome"] == "ok"
    assert result.attempts[1]["registered_fraction"] >= 0.95
    seeds.clear()
    assert sfm_of_frames(folder, meta, tmp_path / "work2", "keyframes", 2) is None
    assert seeds == [0]


def test_frame_set_is_cached_and_reused(room_video, tmp_path):
    """A second ingest of the same frames with another mapper reuses the decoded frames,
    features and matches; a changed stride is another frame set."""
    video, _ = room_video
    cache = tmp_path / "cache"
    first = ingest(video, tmp_path / "a", max_size=None, cache_dir=cache, progress=False)
    assert not first.cached and "features" in first.seconds
    again = ingest(video, tmp_path / "b", max_size=None, cache_dir=cache, mapper="incremental", progress=False)
    assert again.cached and "features" not in again.seconds and again.mapper == "incremental"
    assert again.registered >= 0.9 * again.frames
    frame_sets = lambda: [d for d in cache.iterdir() if not d.name.startswith(".") and d.name != "poses"]  # noqa: E731
    assert len(frame_sets()) == 1
    ingest(video, tmp_path / "c", max_size=None, every=2, cache_dir=cache, progress=False)
    assert len(frame_sets()) == 2


def test_another_size_reuses_the_poses(room_video, tmp_path):
    """A re-run at another `max_size` (auto mapper) decodes the frames at that size and rescales
    the cameras of the model mapped before: no features, no mapping; the same poses, intrinsics
    in the new pixels, every frame's image matching its camera. `--mapper` maps anew."""
    video, _ = room_video
    cache = tmp_path / "cache"
    first = ingest(video, tmp_path / "full", max_size=None, holdout_every=0, cache_dir=cache, progress=False)
    assert first.poses_from is None and (cache / "poses").is_dir()
    small = ingest(video, tmp_path / "small", max_size=96, holdout_every=0, cache_dir=cache, progress=False)
    assert small.poses_from == "keyframes model mapped at full size, rescaled"
    assert "features" not in small.seconds and "mapping" not in small.seconds and "decode" in small.seconds
    assert small.registered == first.registered and small.mapper == first.mapper
    # Reprojection error in the new pixels: the keypoints were rescaled with the cameras.
    assert small.mean_reprojection_error_px == pytest.approx(first.mean_reprojection_error_px * 96 / 160, rel=0.05)
    a, b = load_scene(tmp_path / "full"), load_scene(tmp_path / "small")
    for fa, fb in zip(a.train_frames, b.train_frames):
        assert fa.id == fb.id
        np.testing.assert_allclose(fb.camera.viewmat, fa.camera.viewmat, atol=1e-6)
        assert fb.image().shape[:2] == (fb.camera.height, fb.camera.width)
        assert max(fb.camera.width, fb.camera.height) <= 96
        np.testing.assert_allclose(fb.camera.K[0, 0] / fb.camera.width, fa.camera.K[0, 0] / fa.camera.width, rtol=0.03)
    again = ingest(video, tmp_path / "mapped", max_size=96, holdout_every=0, cache_dir=cache, mapper="keyframes", progress=False)
    assert again.poses_from is None and "mapping" in again.seconds
    # A kept model that cannot be read (its model files, then its metadata) is mapped anew, not an error.
    for corrupt in ("sparse", "poses.json"):
        for kept in (cache / "poses").iterdir():
            for f in (kept / "sparse").iterdir() if corrupt == "sparse" else [kept / "poses.json"]:
                f.write_bytes(b"\x00garbage")
        broken = ingest(video, tmp_path / f"broken-{corrupt}", max_size=96, holdout_every=0, cache_dir=cache, progress=False)
        assert broken.poses_from is None and "mapping" in broken.seconds, corrupt
        assert broken.registered >= 0.9 * broken.frames


def test_one_video_holds_out_its_own_frames(room_video, tmp_path):
    from kgs_core.evaluate import heldout_kind

    video, _ = room_video
    report = ingest(video, tmp_path / "scene", max_size=None, exposure=0.4, progress=False)  # default: every 8th
    scene = load_scene(tmp_path / "scene")
    test_ids = sorted(int(f.id[3:]) for f in scene.test_frames)
    assert test_ids == [4, 12] and len(scene.train_frames) == 14
    assert all(f.camera_id == 0 and f.exposure == pytest.approx(0.4) for f in scene.test_frames)
    assert "same-camera" in report.holdout and "same-camera" in heldout_kind(scene)
    with pytest.raises(SceneError, match="holdout_every"):
        ingest(video, tmp_path / "bad", holdout_every=1, progress=False)


def test_long_video_gets_a_stride(room_video):
    from kgs_core.data.ingest import choose_stride

    video, _ = room_video  # 16 frames
    assert choose_stride(video, None, None, auto_max_frames=100) == (1, "all 16 frames")
    stride, why = choose_stride(video, None, None, auto_max_frames=5)
    assert stride == 3 and "16 frames" in why and "every 3rd" in why and "--every" in why
    assert choose_stride(video, None, None, auto_max_frames=12)[0] == 1  # a third too many: kept whole
    assert choose_stride(video, 3, None, auto_max_frames=5) == (3, "given")
    with pytest.raises(SceneError, match="--every"):
        choose_stride(video, 0, None)


def test_fixed_camera_skips_sfm(room_video, tmp_path):
    video, _ = room_video
    report = ingest(video, tmp_path / "still", max_size=None, fixed_camera=True, holdout_every=0, progress=False)
    scene = load_scene(tmp_path / "still")
    assert report.mapper == "fixed-camera" and len(scene.train_frames) == 16 and len(scene.points) > 1000
    view = scene.train_frames[0].camera.viewmat
    assert all(np.allclose(f.camera.viewmat, view) for f in scene.train_frames)
    # the starting points lie in front of the camera
    z = scene.points @ view[2, :3] + view[2, 3]
    assert (z > 0).all()


def test_undistort_frame_makes_a_radial_camera_pinhole(tmp_path):
    """A pattern seen through a SIMPLE_RADIAL lens (k1 = 0.12, like the BARD-GS cameras) comes
    out of the undistorter as the same pattern through the returned pinhole camera."""
    import pycolmap
    from PIL import Image

    from kgs_core.data.ingest import undistort_frame

    w, h = 160, 96
    cam = pycolmap.Camera(model="SIMPLE_RADIAL", width=w, height=h, params=[110.0, w / 2, h / 2, 0.12])

    def pattern(xn, yn):
        return 0.5 + 0.5 * np.sin(9 * xn) * np.sin(9 * yn)

    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    normalized = np.asarray(cam.cam_from_img(np.stack([u.ravel(), v.ravel()], 1)))
    distorted = pattern(normalized[:, 0], normalized[:, 1]).reshape(h, w)
    path = tmp_path / "frame.png"
    Image.fromarray(np.repeat((distorted * 255).round().astype(np.uint8)[..., None], 3, 2)).save(path)

    pinhole, pixels = undistort_frame(cam, path)
    assert pinhole.model_name == "PINHOLE" and pixels.shape == (pinhole.height, pinhole.width, 3)
    fx, fy, cx, cy = pinhole.params
    uu, vv = np.meshgrid(np.arange(pinhole.width) + 0.5, np.arange(pinhole.height) + 0.5)
    expected = pattern((uu - cx) / fx, (vv - cy) / fy)
    got = pixels[..., 0] / 255.0
    inner = (slice(3, -3), slice(3, -3))  # bilinear resampling at the crop border
    err = np.abs(got - expected)[inner].mean()
    # Reading the distorted frame as if it were pinhole is what undistortion fixes.
    K_err = np.abs(distorted - pattern((u - w / 2) / 110.0, (v - h / 2) / 110.0)).mean()
    assert err < 0.03 and K_err > 3 * err, (err, K_err)


def synthetic_reconstruction(true_lens: str, true_params: list[float], seed: int = 0):
    """A pycolmap model of 12 views of 300 points, observed through `true_lens` (with 0.05 px of
    keypoint noise), adjusted with a SIMPLE_RADIAL camera, as the mappers leave it."""
    import pycolmap

    rng = np.random.default_rng(seed)
    w, h = 320, 180
    truth = pycolmap.Camera(model=true_lens, width=w, height=h, params=true_params)
    f = float(true_params[0])
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="SIMPLE_RADIAL", width=w, height=h, params=[f, w / 2, h / 2, 0.0], camera_id=1))
    points = rng.uniform([-1.5, -0.8, 3], [1.5, 0.8, 6], (300, 3))
    ids = [rec.add_point3D(p, pycolmap.Track(), np.array([128, 128, 128], np.uint8)) for p in points]
    for i in range(12):
        # A hand-held path: yaw, pitch and roll all vary (with yaw alone, stretching the scene
        # along x would trade against fx / fy).
        a = np.radians([-10 + 20 * i / 11, 6 * np.sin(i), 15 * np.cos(1.3 * i)])
        R = (
            pycolmap.Rotation3d(np.array([0, 1.0, 0]) * a[0]).matrix()
            @ pycolmap.Rotation3d(np.array([1.0, 0, 0]) * a[1]).matrix()
            @ pycolmap.Rotation3d(np.array([0, 0, 1.0]) * a[2]).matrix()
        )
        t = np.array([0.15 * i - 0.8, 0.1 * np.cos(i), 0.0])
        cam_points = points @ R.T + t
        keypoints = np.asarray(truth.img_from_cam(cam_points)) + rng.normal(0, 0.05, (len(points), 2))
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=f"f{i:05d}_a.png", keypoints=keypoints, camera_id=1, image_id=i + 1),
            pycolmap.Rigid3d(pycolmap.Rotation3d(R), t),
        )
        for j, pid in enumerate(ids):
            rec.add_observation(pid, pycolmap.TrackElement(i + 1, j))
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = ba.refine_extra_params = True
    pycolmap.bundle_adjustment(rec, ba)
    return rec


def test_lens_refit_recovers_non_square_pixels():
    """A camera with non-square pixels and a decentred lens (OPENCV fx/fy = 1.04, p1 = 0.004),
    as the BARD-GS pairs have, mapped as SIMPLE_RADIAL: the refit finds its aspect and lowers the
    reprojection error to the keypoint noise; the mapped model is left unchanged."""
    from kgs_core.data.lens import LENS_ITERATIONS, refine_lens

    rec = synthetic_reconstruction("OPENCV", [208.0, 200.0, 160.0, 90.0, 0.05, 0.0, 0.004, 0.0])
    rec.update_point_3d_errors()
    before = rec.compute_mean_reprojection_error()
    refit, report = refine_lens(rec)
    assert report["kept"] and report["after_px"] < 0.3 * report["before_px"], report
    assert report["iterations"] == LENS_ITERATIONS  # past the probe: a lens worth refitting
    assert report["after_px"] < 0.15  # the keypoint noise is 0.05 px per axis
    fx, fy = refit.cameras[1].params[:2]
    assert fx / fy == pytest.approx(1.04, rel=0.005)
    assert rec.cameras[1].model_name == "SIMPLE_RADIAL" and rec.compute_mean_reprojection_error() == before


def test_lens_refit_keeps_a_lens_the_mapper_fits():
    """A lens SIMPLE_RADIAL already describes: the larger model gains nothing worth keeping."""
    from kgs_core.data.lens import LENS_PROBE_ITERATIONS, refine_lens

    rec = synthetic_reconstruction("SIMPLE_RADIAL", [200.0, 160.0, 90.0, 0.05])
    refit, report = refine_lens(rec)
    assert not report["kept"] and "under 3%" in report["reason"], report
    assert report["iterations"] == LENS_PROBE_ITERATIONS  # the probe found nothing to gain: stopped there
    assert refit is rec


def test_lens_refit_follows_the_keyframe_probe():
    """The keyframe model's probe decides whether the whole model is refitted: a probe that
    gained nothing skips the refit (the model returned as it is, the probe in the report), one
    that gained goes on to the whole model's refit."""
    from kgs_core.data.lens import LENS_PROBE_ITERATIONS, lens_gain, refine_lens

    whole = synthetic_reconstruction("OPENCV", [208.0, 200.0, 160.0, 90.0, 0.05, 0.0, 0.004, 0.0])
    # Keyframe models: other draws of the views, through a lens SIMPLE_RADIAL describes / the same lens.
    _, flat = refine_lens(synthetic_reconstruction("SIMPLE_RADIAL", [200.0, 160.0, 90.0, 0.05], seed=1), iterations=LENS_PROBE_ITERATIONS)
    _, steep = refine_lens(
        synthetic_reconstruction("OPENCV", [208.0, 200.0, 160.0, 90.0, 0.05, 0.0, 0.004, 0.0], seed=1), iterations=LENS_PROBE_ITERATIONS
    )
    assert lens_gain(flat) < 0.03 < lens_gain(steep)

    skipped, report = refine_lens(whole, probe=flat)
    assert skipped is whole and not report["kept"] and "keyframe model" in report["reason"], report
    assert report["probe"] is flat and "after_px" not in report

    refit, report = refine_lens(whole, probe=steep)
    assert report["kept"] and refit is not whole and report["probe"] is steep
    # A probe without a result (its adjustment failed) decides nothing.
    assert lens_gain({"before_px": 1.0, "kept": False, "reason": "the adjustment failed"}) is None
    assert refine_lens(whole, probe={"before_px": 1.0, "kept": False})[1]["kept"]


def test_the_global_mapper_maps_the_video(room_video, tmp_path):
    """`--mapper global` (GLOMAP) runs through pycolmap's own options (its pipeline has no
    triangulator of its own to seed) and poses the clip."""
    video, _ = room_video
    report = ingest(video, tmp_path / "scene", max_size=None, exposure=0.0, holdout_every=0, mapper="global", progress=False)
    assert report.mapper == "global" and report.attempts[0]["outcome"] == "ok"
    assert report.registered_fraction >= 0.9 and report.mean_reprojection_error_px < 1.5


def test_a_keyframe_model_with_a_strong_radial_term_gets_a_second_opinion_and_the_better_fit_is_kept(room_video, tmp_path, monkeypatch):
    """A long focal length with strong pincushion and the true lens reproject almost alike, and
    the keyframe mapper settles in either: where the keyframe model's radial term is strong (here:
    made so), auto maps the frames with the incremental mapper too and keeps the model that
    reprojects better, both attempts recorded with their errors. A weak one maps once."""
    from kgs_core.data import sfm
    from kgs_core.data.frame_cache import frame_set

    video, _ = room_video
    folder, meta, _ = frame_set(video, None, 1, None, None, tmp_path / "cache", False, tmp_path)
    once = sfm_of_frames(folder, meta, tmp_path / "work", "auto", 4)
    assert [a["mapper"] for a in once.attempts] == ["keyframes"] and sfm.strong_radial(once.rec) is None
    real = sfm.map_keyframes

    def pincushion(*args, **kw):
        rec = real(*args, **kw)
        for cam in rec.cameras.values():
            params = cam.params.copy()
            params[3] = 2 * sfm.STRONG_RADIAL
            cam.params = params
        return rec

    monkeypatch.setattr(sfm, "map_keyframes", pincushion)
    result = sfm_of_frames(folder, meta, tmp_path / "work2", "auto", 4)
    first, second = result.attempts
    assert (first["mapper"], second["mapper"]) == ("keyframes", "incremental") and result.mapper == "incremental"
    assert first["outcome"] == second["outcome"] == "ok" and first["reprojection_px"] > second["reprojection_px"]
    assert sfm.strong_radial(result.rec) is None
    assert sfm.reprojection_px(result.rec) == pytest.approx(second["reprojection_px"], abs=1e-3)
    # An explicit mapper is what runs.
    assert [a["mapper"] for a in sfm_of_frames(folder, meta, tmp_path / "work3", "keyframes", 4).attempts] == ["keyframes"]


def rig_reconstruction(jitter_deg: float, focal: float = 500.0, times: int = 20, seed: int = 0):
    """A pycolmap model of two synchronised cameras (`fNNNNN_a.png`, `fNNNNN_b.png`) on a rig: b
    is a fixed turn and offset from a, each time turned once more by `jitter_deg` about a random axis."""
    import pycolmap

    rng = np.random.default_rng(seed)
    rec = pycolmap.Reconstruction()
    for cam_id in (1, 2):
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(model="SIMPLE_RADIAL", width=640, height=360, params=[focal, 320, 180, 0.0], camera_id=cam_id)
        )
    rig = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.02, -0.3, 0.01])), np.array([0.05, 0.0, 0.0]))
    for i in range(times):
        a = pycolmap.Rigid3d(pycolmap.Rotation3d(rng.normal(0, 0.3, 3)), rng.normal(0, 1, 3))
        axis = rng.normal(size=3)
        jitter = pycolmap.Rigid3d(pycolmap.Rotation3d(axis / np.linalg.norm(axis) * np.radians(jitter_deg)), np.zeros(3))
        for cam_id, pose in ((1, a), (2, jitter * rig * a)):
            name = f"f{i:05d}_{'ab'[cam_id - 1]}.png"
            rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=cam_id, image_id=2 * i + cam_id), pose)
    return rec


def test_the_rig_spread_is_the_second_camera_s_turn_against_the_first_in_pixels():
    """Two cameras fixed together: the spread of b's pose relative to a's over the clip, as
    pixels at a's focal length (angle × focal), whatever the rig's own turn and offset."""
    from kgs_core.data import sfm

    assert sfm.rig_spread_px(rig_reconstruction(0.0)) == pytest.approx(0.0, abs=1e-3)
    for jitter, focal in ((0.5, 500.0), (0.5, 1500.0), (1.0, 500.0)):
        expected = np.radians(jitter) * focal
        # The median angle from the mean turn: the jitter itself, less what the mean absorbed.
        assert sfm.rig_spread_px(rig_reconstruction(jitter, focal)) == pytest.approx(expected, rel=0.15), (jitter, focal)
    one_camera = rig_reconstruction(1.0)
    for im in list(one_camera.images.values()):
        if im.name.endswith("_b.png"):
            one_camera.deregister_frame(im.frame_id)
    assert sfm.rig_spread_px(one_camera) is None


def test_a_keyframe_model_with_a_loose_rig_gets_a_second_opinion_and_the_tighter_rig_is_kept(tmp_path, monkeypatch):
    """A second camera that turns against the first by more than LOOSE_RIG_PX over the clip is a
    model that misplaces one of them: auto maps the frames with the incremental mapper too and
    keeps the tighter rig, even where the loose one reprojects better; both spreads are recorded.
    A tight rig maps once."""
    from kgs_core.data import sfm

    loose_deg = 2 * np.degrees(sfm.LOOSE_RIG_PX / 500.0)
    made = {"keyframes": rig_reconstruction(loose_deg), "incremental": rig_reconstruction(0.2, seed=1)}
    monkeypatch.setattr(sfm, "map_keyframes", lambda *args, **kw: made["keyframes"])
    monkeypatch.setattr(sfm, "map_incremental", lambda *args: made["incremental"])
    fits = {id(made["keyframes"]): 0.5, id(made["incremental"]): 1.5}  # the loose rig reprojects better
    monkeypatch.setattr(sfm, "reprojection_px", lambda rec: fits[id(rec)])
    names_a = [f"f{i:05d}_a.png" for i in range(20)]
    names_b = [n.replace("_a.", "_b.") for n in names_a]
    result = sfm.run_sfm(tmp_path / "database.db", tmp_path, tmp_path / "work", names_a, names_b, {}, "auto", progress=False)
    first, second = result.attempts
    assert (first["mapper"], second["mapper"]) == ("keyframes", "incremental") and result.mapper == "incremental"
    assert first["rig_spread_px"] > sfm.LOOSE_RIG_PX > second["rig_spread_px"]
    made["keyframes"] = rig_reconstruction(0.2, seed=2)
    fits[id(made["keyframes"])] = 0.5
    again = sfm.run_sfm(tmp_path / "database.db", tmp_path, tmp_path / "work2", names_a, names_b, {}, "auto", progress=False)
    assert [a["mapper"] for a in again.attempts] == ["keyframes"]
