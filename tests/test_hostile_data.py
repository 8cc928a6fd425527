"""Hostile dataset content: whatever a dataset's JSON and images hold, loading it either
works or raises a `SceneError` that names the file (and the field), never another exception
(an uploaded zip reaches these loaders through the server)."""

from __future__ import annotations

import json
import os
import shutil
import struct
import tempfile
import zlib
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kgs_core.data.formats import load_scene
from kgs_core.data.scene import SceneError
from kgs_core.data.synth.generate import synthesize

JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(10**20), 10**20) | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=6),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=10,
)
# Deterministic in CI; KGS_HYPOTHESIS_EXAMPLES=1000 searches harder by hand.
SETTINGS = settings(
    max_examples=int(os.environ.get("KGS_HYPOTHESIS_EXAMPLES", 60)),
    derandomize=True,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    return synthesize("bounce", tmp_path_factory.mktemp("hostile") / "bounce", blur="none", size=32, frames=4, subframes=1, progress=False)


def load_edited(scene_dir: Path, rel: str, edit, fmt: str) -> None:
    """Copies the scene, applies `edit` to the JSON file `rel`, loads it: a SceneError naming
    the edited file is fine, any other exception fails the test."""
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "s"
        shutil.copytree(scene_dir, root)
        path = root / rel
        js = json.loads(path.read_text())
        path.write_text(json.dumps(edit(js)))
        try:
            load_scene(root, fmt=fmt)
        except SceneError as exc:
            assert str(exc), "a SceneError says what is wrong"


@SETTINGS
@given(
    key=st.sampled_from(["file_path", "time", "exposure", "camera_id", "id", "transform_matrix", "sharp_file_path", "mask_file_path"]),
    value=JSON,
)
def test_dnerf_frame_fields(scene_dir, key, value):
    def edit(js):
        js["frames"][1][key] = value
        return js

    load_edited(scene_dir, "transforms_train.json", edit, "dnerf")


@SETTINGS
@given(key=st.sampled_from(["camera_angle_x", "frames"]), value=JSON)
def test_dnerf_top_level(scene_dir, key, value):
    load_edited(scene_dir, "transforms_train.json", lambda js: {**js, key: value}, "dnerf")


@SETTINGS
@given(key=st.sampled_from(["time", "exposure", "camera_id", "warp_id", "time_id"]), value=JSON, drop_time=st.booleans())
def test_nerfies_metadata_fields(scene_dir, key, value, drop_time):
    def edit(js):
        frame = js["c0_00001"]
        if drop_time:
            for f in js.values():
                f.pop("time", None)
        frame[key] = value
        return js

    load_edited(scene_dir, "metadata.json", edit, "nerfies")


@SETTINGS
@given(
    key=st.sampled_from(
        [
            "focal_length",
            "principal_point",
            "image_size",
            "orientation",
            "position",
            "skew",
            "pixel_aspect_ratio",
            "radial_distortion",
            "tangential_distortion",
        ]
    ),
    value=JSON,
)
def test_nerfies_camera_fields(scene_dir, key, value):
    load_edited(scene_dir, "camera/c0_00001.json", lambda js: {**js, key: value}, "nerfies")


@SETTINGS
@given(rel=st.sampled_from(["metadata.json", "dataset.json", "camera/c0_00000.json", "scene.json"]), value=JSON)
def test_whole_files_replaced(scene_dir, rel, value):
    load_edited(scene_dir, rel, lambda js: value, "nerfies")


@SETTINGS
@given(key=st.sampled_from(["ids", "train_ids", "val_ids"]), value=JSON)
def test_nerfies_dataset_fields(scene_dir, key, value):
    load_edited(scene_dir, "dataset.json", lambda js: {**js, key: value}, "nerfies")


def test_deep_json_and_decompression_bomb(scene_dir, tmp_path):
    root = tmp_path / "s"
    shutil.copytree(scene_dir, root)
    (root / "metadata.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(SceneError, match=r"metadata\.json: JSON nested too deeply"):
        load_scene(root, fmt="nerfies")
    shutil.rmtree(root)
    shutil.copytree(scene_dir, root)
    # A valid PNG header that claims 100000 x 100000 pixels.
    ihdr = struct.pack(">IIBBBBB", 100_000, 100_000, 8, 2, 0, 0, 0)
    chunk = lambda kind, data: struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))  # noqa: E731
    (root / "rgb" / "1x" / "c0_00001.png").write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b""))
    with pytest.raises(SceneError, match=r"c0_00001\.png"):
        load_scene(root, fmt="dnerf")


@pytest.fixture(scope="module")
def colmap_dir(scene_dir, tmp_path_factory) -> Path:
    from kgs_core.data.formats import write_colmap

    root = tmp_path_factory.mktemp("hostile-colmap") / "c"
    write_colmap(load_scene(scene_dir), root)
    return root


def load_colmap_edited(colmap_dir: Path, rel: str, edit) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "c"
        shutil.copytree(colmap_dir, root)
        path = root / rel
        path.write_text(json.dumps(edit(json.loads(path.read_text()) if path.is_file() else {})))
        try:
            load_scene(root, fmt="colmap")
        except SceneError as exc:
            assert str(exc), "a SceneError says what is wrong"


@SETTINGS
@given(key=st.sampled_from(["time", "exposure", "camera_id", "split"]), value=JSON, whole=st.booleans())
def test_colmap_times_fields(colmap_dir, key, value, whole):
    def edit(js):
        first = next(iter(js))
        js[first] = value if whole else {**js[first], key: value}
        return js

    load_colmap_edited(colmap_dir, "times.json", edit)


@SETTINGS
@given(rel=st.sampled_from(["times.json", "kgs.json"]), value=JSON)
def test_colmap_whole_files_replaced(colmap_dir, rel, value):
    load_colmap_edited(colmap_dir, rel, lambda js: value)
