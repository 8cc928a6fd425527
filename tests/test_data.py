"""Scene data: the synthetic generator, the dataset formats (round trips), bad input."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from kgs_core.data.formats import detect_format, load_scene, write_colmap, write_dnerf, write_nerfies
from kgs_core.data.scene import SceneError
from kgs_core.data.synth.generate import synthesize


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """A small blurry bounce scene: 6 frames, 48 px, 4 sub-frames."""
    return synthesize("bounce", tmp_path_factory.mktemp("syn") / "bounce", blur="severe", size=48, frames=6, subframes=4, progress=False)


def frames_by_id(scene):
    return {f.id: f for f in scene.frames}


def assert_same_scene(a, b, atol=1e-9):
    fa, fb = frames_by_id(a), frames_by_id(b)
    assert fa.keys() == fb.keys()
    for k, f in fa.items():
        g = fb[k]
        assert abs(f.time - g.time) < atol and f.split == g.split and f.camera_id == g.camera_id
        assert abs(f.exposure - g.exposure) < atol
        np.testing.assert_allclose(f.camera.viewmat, g.camera.viewmat, atol=1e-7)
        np.testing.assert_allclose(f.camera.K, g.camera.K, atol=1e-7)
        assert (f.camera.width, f.camera.height) == (g.camera.width, g.camera.height)
        np.testing.assert_array_equal(f.image(), g.image())


def test_synthetic_scene_contents(tiny):
    scene = load_scene(tiny)
    assert scene.source_format == "nerfies" and scene.extras["generator"]["scene"] == "bounce"
    assert len(scene.train_frames) == 6 and len(scene.test_frames) == 6
    assert scene.exposure == 1.0 and all(f.exposure == 0 for f in scene.test_frames)
    assert abs(scene.dt - 1 / 5) < 1e-9
    assert len(scene.points) > 100 and scene.points.shape == scene.point_colors.shape
    # Normalised: cameras within a unit-ish sphere.
    centres = np.stack([f.camera.center for f in scene.frames])
    assert np.linalg.norm(centres, axis=1).max() <= 1.0 + 1e-6
    for f in scene.frames:
        assert f.sharp_path and f.mask_path and f.motion_path
        assert f.image().shape == (48, 48, 3) and f.mask().shape == (48, 48) and f.motion().shape == (48, 48, 2)
    # The ball moves: some dynamic pixels with non-zero motion in every training frame.
    for f in scene.train_frames:
        m = f.mask()
        assert m.any() and np.abs(f.motion()[m]).max() > 0.1


def test_blur_is_the_mean_over_the_exposure(tiny, tmp_path):
    scene = load_scene(tiny)
    f = scene.train_frames[2]
    blurry, sharp = f.image(), f.sharp()
    # Blur changes the moving ball's pixels far more than the (shaking) background.
    diff = np.abs(blurry - sharp).mean(-1)
    assert diff[f.mask()].mean() > 2 * diff[~f.mask()].mean()
    # Without blur the training image is the sharp one.
    sharp_scene = synthesize("bounce", tmp_path / "sharp", blur="none", size=48, frames=3, progress=False)
    for g in load_scene(sharp_scene).frames:
        np.testing.assert_array_equal(g.image(), g.sharp())


def test_sharp_frames_integrate_over_the_pixel(tmp_path):
    """A camera's pixel averages the light over its area. The sharp frames hold the detail of that
    area integral (an 8 x 8 grid of rays a pixel stands in for it), not the false detail of one ray
    through each centre, which aliases the textures' checker edges into pixel-high steps."""
    from kgs_core.data.synth.generate import grid_offsets, render
    from kgs_core.data.synth.scenes import build_world, heldout_camera, intrinsics
    from kgs_core.evaluate import gradient_energy

    size = 40
    scene = load_scene(synthesize("panel", tmp_path / "p", blur="none", size=size, frames=2, progress=False))
    f = scene.test_frames[0]
    world, K, view = build_world("panel", 0), intrinsics(size, size), heldout_camera()(f.time)
    area = np.mean([render(world, view, K, size, size, f.time, p).color for p in grid_offsets(8)], axis=0)
    point = render(world, view, K, size, size, f.time).color
    everywhere = np.ones((size, size), bool)
    energy = lambda img: gradient_energy(img, everywhere) / gradient_energy(area, everywhere)
    assert energy(point) > 1.3  # one ray a pixel: aliased
    assert abs(energy(f.sharp()) - 1) < 0.12
    np.testing.assert_allclose(f.sharp(), area, atol=0.08)  # (8-bit PNG, 3 x 3 against 8 x 8 rays)
    # The masks still come from the centre ray: inside or outside the moving object, nothing between.
    assert set(np.unique(f.mask())) <= {False, True}


def test_generator_is_deterministic(tmp_path):
    a = synthesize("die", tmp_path / "a", blur="mild", size=32, frames=3, subframes=2, seed=3, progress=False)
    b = synthesize("die", tmp_path / "b", blur="mild", size=32, frames=3, subframes=2, seed=3, progress=False)
    c = synthesize("die", tmp_path / "c", blur="mild", size=32, frames=3, subframes=2, seed=4, progress=False)
    for p in sorted((a / "rgb" / "1x").iterdir()):
        assert p.read_bytes() == (b / "rgb" / "1x" / p.name).read_bytes()
    assert any(p.read_bytes() != (c / "rgb" / "1x" / p.name).read_bytes() for p in (a / "rgb" / "1x").iterdir())


@pytest.mark.parametrize("name", ["die", "top", "sheet", "cross", "swing", "spin", "panel", "fastpanel", "room"])
def test_every_named_scene_renders(name, tmp_path):
    out = synthesize(name, tmp_path / name, blur="mild", size=32, frames=2, subframes=2, progress=False)
    scene = load_scene(out)
    masks = [f.mask() for f in scene.frames]
    if name == "room":
        assert not any(m.any() for m in masks) and scene.extras["generator"]["dynamic_objects"] == []
    else:
        assert any(m.any() for m in masks)


def test_fastpanel_moves_twice_as_far_as_panel(tmp_path):
    """The blur-magnitude control of the quality benchmark: the same panel, twice the swing."""
    speeds = {}
    for name in ("panel", "fastpanel"):
        scene = load_scene(synthesize(name, tmp_path / name, blur="none", size=32, frames=8, subframes=1, progress=False))
        frames = [f for f in scene.train_frames if f.mask() is not None and f.mask().any()]
        speeds[name] = np.mean([np.linalg.norm(f.motion()[f.mask()], axis=-1).mean() for f in frames])
    assert 1.6 < speeds["fastpanel"] / speeds["panel"] < 2.4, speeds  # (1.88 measured)


def test_spin_turns_three_times_about_its_own_axis_while_its_centre_drifts_straight():
    """The stand-in for a toy spinning on a table: the rotation is about the toy's own vertical
    axis through its centre (the centre moves on a line, at constant speed, whatever the spin),
    three whole turns over the clip, and only the toy is dynamic."""
    from kgs_core.data.synth.scenes import spin

    table, toy = spin(0)
    assert toy.dynamic and not table.dynamic
    ts = np.linspace(0, 1, 61)
    poses = np.stack([toy.pose(t) for t in ts])
    centres = poses[:, :3, 3]
    steps = np.diff(centres, axis=0)
    np.testing.assert_allclose(steps, np.broadcast_to(steps[0], steps.shape), atol=1e-12)  # straight, uniform
    assert np.linalg.norm(centres[-1] - centres[0]) > 0.5
    axis = poses[:, :3, 2]  # the toy's own z axis stays vertical: it spins about it
    np.testing.assert_allclose(axis, np.broadcast_to([0, 0, 1], axis.shape), atol=1e-12)
    angle = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    assert abs(angle[-1] - angle[0] - 3 * 2 * np.pi) < 1e-9
    assert np.all(np.diff(angle) > 0)  # one direction, no reversal
    # It rests on the table top: its lowest point is the table's top face.
    assert abs(centres[0, 2] - toy.shape.half[2] - 2 * table.shape.half[2]) < 1e-12


def test_bounce_reverses_velocity_inside_a_frame():
    from kgs_core.data.synth.scenes import BOUNCE_IMPACTS, bounce

    ball = bounce(0)[0]
    for ti in BOUNCE_IMPACTS:
        frame = ti * 59  # default 60 frames: impacts fall between frame times
        assert 0.1 < frame % 1 < 0.9
        z = [ball.pose(t)[2, 3] for t in (ti - 0.01, ti, ti + 0.01)]
        assert z[0] > z[1] < z[2]  # down, then up


def test_nerfies_round_trip(tiny, tmp_path):
    scene = load_scene(tiny)
    write_nerfies(scene, tmp_path / "copy")
    again = load_scene(tmp_path / "copy")
    assert_same_scene(scene, again)
    np.testing.assert_allclose(again.points, scene.points)
    f = frames_by_id(again)["c0_00002"]
    np.testing.assert_array_equal(f.mask(), frames_by_id(scene)["c0_00002"].mask())
    np.testing.assert_array_equal(f.motion(), frames_by_id(scene)["c0_00002"].motion())


def test_dnerf_round_trip(tiny, tmp_path):
    scene = load_scene(tiny)
    assert_same_scene(scene, load_scene(tiny, fmt="dnerf"))  # the generator wrote both layouts
    dst = tmp_path / "dnerf"
    shutil.copytree(tiny / "rgb", dst / "rgb")
    moved = [
        replace(f, image_path=dst / "rgb" / "1x" / f.image_path.name, sharp_path=None, mask_path=None, motion_path=None)
        for f in scene.frames
    ]
    scene.frames = moved
    write_dnerf(scene, dst)
    assert detect_format(dst) == "dnerf"
    assert_same_scene(scene, load_scene(dst, normalize=False))


def test_colmap_round_trip(tiny, tmp_path):
    scene = load_scene(tiny)
    write_colmap(scene, tmp_path / "colmap")
    assert detect_format(tmp_path / "colmap") == "colmap"
    again = load_scene(tmp_path / "colmap", normalize=False)
    assert_same_scene(scene, again)
    order = lambda p: p[np.lexsort(p.T[::-1])]  # COLMAP does not keep point order
    np.testing.assert_allclose(order(again.points), order(scene.points), atol=1e-9)


def test_normalisation_is_recorded_and_composes(tiny, tmp_path):
    scene = load_scene(tiny)
    write_colmap(scene, tmp_path / "c")
    raw = load_scene(tmp_path / "c", normalize=False)
    normed = load_scene(tmp_path / "c")  # normalised again: coordinates barely change
    x = raw.points[:5]
    np.testing.assert_allclose(normed.normalization.apply_points(x), normed.points[:5], atol=1e-9)
    assert abs(normed.normalization.scale - 1) < 0.2


# ---------------------------------------------------------------- bad input


def break_json(path: Path, edit) -> None:
    js = json.loads(path.read_text())
    edit(js)
    path.write_text(json.dumps(js))


@pytest.fixture
def copy(tiny, tmp_path) -> Path:
    dst = tmp_path / "broken"
    shutil.copytree(tiny, dst)
    return dst


def test_missing_dataset(tmp_path):
    with pytest.raises(SceneError, match="not found"):
        load_scene(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SceneError, match="unknown dataset layout"):
        load_scene(tmp_path / "empty")


def test_corrupt_json_names_the_file(copy):
    (copy / "dataset.json").write_text("{not json")
    with pytest.raises(SceneError, match="dataset.json: invalid JSON"):
        load_scene(copy)


def test_missing_camera_field_names_file_and_field(copy):
    break_json(copy / "camera" / "c0_00001.json", lambda js: js.pop("focal_length"))
    with pytest.raises(SceneError, match=r"c0_00001\.json: missing field 'focal_length'"):
        load_scene(copy)


def test_bad_rotation_is_rejected(copy):
    break_json(copy / "camera" / "c0_00001.json", lambda js: js.update(orientation=[[2, 0, 0], [0, 1, 0], [0, 0, 1]]))
    with pytest.raises(SceneError, match="c0_00001: camera rotation"):
        load_scene(copy)


def test_non_monotonic_time(copy):
    def swap(js):
        js["c0_00001"]["time"], js["c0_00003"]["time"] = js["c0_00003"]["time"], js["c0_00001"]["time"]

    break_json(copy / "metadata.json", swap)
    with pytest.raises(SceneError, match=r"metadata\.json: camera 0: time goes backwards at frame c0_00002"):
        load_scene(copy)


def test_time_outside_unit_interval(copy):
    break_json(copy / "metadata.json", lambda js: js["c0_00002"].update(time=1.5))
    with pytest.raises(SceneError, match=r"c0_00002: time 1.5 outside \[0, 1\]"):
        load_scene(copy)


def test_non_monotonic_time_in_dnerf(copy):
    def swap(js):
        js["frames"][1]["time"], js["frames"][3]["time"] = 0.9, 0.1

    break_json(copy / "transforms_train.json", swap)
    scene = load_scene(copy, fmt="dnerf")  # D-NeRF frames are re-ordered by time: allowed
    assert [f.time for f in scene.train_frames] == sorted(f.time for f in scene.train_frames)


def test_corrupt_image_names_the_file(copy):
    (copy / "rgb" / "1x" / "c0_00002.png").write_bytes(b"not a png")
    scene = load_scene(copy)
    with pytest.raises(ValueError, match=r"c0_00002\.png"):
        frames_by_id(scene)["c0_00002"].image()


def test_missing_image_names_the_file(copy):
    (copy / "rgb" / "1x" / "c0_00002.png").unlink()
    with pytest.raises(SceneError, match=r"image not found: .*c0_00002"):
        load_scene(copy)


def test_unsupported_camera_model(tiny, tmp_path):
    import pycolmap

    scene = load_scene(tiny)
    write_colmap(scene, tmp_path / "c")
    rec = pycolmap.Reconstruction(str(tmp_path / "c" / "sparse" / "0"))
    for cam in rec.cameras.values():
        cam.model = pycolmap.CameraModelId.OPENCV_FISHEYE
        cam.params = [40.0, 40.0, 24.0, 24.0, 0.0, 0.0, 0.0, 0.0]
    rec.write(str(tmp_path / "c" / "sparse" / "0"))
    with pytest.raises(SceneError, match="unsupported camera model OPENCV_FISHEYE"):
        load_scene(tmp_path / "c")


def test_generator_rejects_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="unknown scene"):
        synthesize("teapot", tmp_path / "x", progress=False)
    with pytest.raises(ValueError, match="blur"):
        synthesize("die", tmp_path / "x", blur="extreme", progress=False)
    assert not (tmp_path / "x").exists()


def test_output_is_atomic(tmp_path, monkeypatch):
    """A failure half-way leaves no dataset folder behind."""
    import kgs_core.data.synth.generate as gen

    calls = {"n": 0}
    real = gen.write_mask

    def failing(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("disk full")
        return real(*a, **k)

    monkeypatch.setattr(gen, "write_mask", failing)
    with pytest.raises(RuntimeError, match="disk full"):
        synthesize("die", tmp_path / "x", size=16, frames=3, subframes=1, progress=False)
    assert not (tmp_path / "x").exists()
    assert not list(tmp_path.iterdir())  # no temporary leftovers either


def test_existing_output_is_not_overwritten(tiny):
    with pytest.raises(FileExistsError):
        synthesize("bounce", tiny, size=16, frames=2, progress=False)


@pytest.mark.parametrize("bad", ["/etc/hostname", "../outside", "./rgb/../../outside"])
@pytest.mark.parametrize("key", ["file_path", "sharp_file_path", "mask_file_path", "motion_file_path"])
def test_dnerf_paths_stay_inside_the_dataset(copy, bad, key):
    """A dataset names only its own files: an absolute path or one that climbs out is refused,
    naming the field (an uploaded zip could otherwise make the server read any file)."""
    (copy.parent / "outside.png").write_bytes((copy / "rgb" / "1x" / "c0_00000.png").read_bytes())
    break_json(copy / "transforms_train.json", lambda js: js["frames"][1].update({key: bad}))
    with pytest.raises(SceneError, match=rf"transforms_train\.json frames\[1\] field '{key}'.*(absolute path|leaves the dataset)"):
        load_scene(copy, fmt="dnerf")


def test_symlink_out_of_the_dataset_is_refused(copy):
    outside = copy.parent / "secret.png"
    outside.write_bytes((copy / "rgb" / "1x" / "c0_00000.png").read_bytes())
    img = copy / "rgb" / "1x" / "c0_00002.png"
    img.unlink()
    img.symlink_to(outside)
    for fmt in ("nerfies", "dnerf"):
        with pytest.raises(SceneError, match="leaves the dataset folder"):
            load_scene(copy, fmt=fmt)


def test_nerfies_ids_cannot_climb_out(copy):
    evil = "../../../etc/passwd"
    break_json(copy / "dataset.json", lambda js: js.update(ids=js["ids"] + [evil]))
    break_json(copy / "metadata.json", lambda js: js.update({evil: {**js["c0_00000"], "time": 1.0}}))
    with pytest.raises(SceneError, match=r"dataset\.json id '\.\./\.\./\.\./etc/passwd'.*leaves the dataset folder"):
        load_scene(copy)
