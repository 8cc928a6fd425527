"""Video ingest: SfM on a synthetic textured video recovers the cameras; bad videos fail clearly."""

from __future__ import annotations

import numpy as np
import pytest

from kgs_core.data.formats import load_scene
from kgs_core.data.ingest import ingest
from kgs_core.data.scene import SceneError
from kgs_core.data.synth.generate import synthesize
from kgs_core.data.video import decode_video, encode_video


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising |s R src + t - dst|^2."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(xd.T @ xs / len(src))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = (S * np.diag(D)).sum() / (xs**2).sum(1).mean()
    return s, R, mu_d - s * R @ mu_s


@pytest.fixture(scope="module")
def room_video(tmp_path_factory):
    root = tmp_path_factory.mktemp("sfm")
    syn = synthesize("room", root / "room", blur="none", size=160, frames=16, progress=False)
    gt = load_scene(syn)
    frames = [(f.image() * 255).round().astype(np.uint8) for f in gt.train_frames]
    return encode_video(frames, root / "room.mp4", fps=12), gt


def test_video_round_trip(room_video):
    video, gt = room_video
    frames = decode_video(video, progress=False)
    assert len(frames) == len(gt.train_frames) and frames[0].shape == (160, 160, 3)
    err = np.abs(frames[3].astype(float) / 255 - gt.train_frames[3].image()).mean()
    assert err < 0.03  # lossy H.264, but the same picture


def test_sfm_recovers_camera_centres(room_video, tmp_path):
    video, gt = room_video
    report = ingest(video, tmp_path / "scene", max_size=None, exposure=0.0, progress=False)
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
    with pytest.raises(SceneError, match="structure from motion"):
        ingest(video, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


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
