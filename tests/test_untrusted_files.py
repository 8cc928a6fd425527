"""Files the product reads that anyone may have written (an uploaded zip, a copied workspace, a
downloaded run): they run no code and reach no file outside their own folder."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from kgs_core.data.formats import load_scene
from kgs_core.data.scene import SceneError
from kgs_core.data.synth.generate import synthesize
from kgs_core.run import RunError, load_run, load_torch, write_run_json


def test_a_pickled_model_or_checkpoint_runs_no_code(tmp_path, runs_code):
    RunsCode = runs_code
    marker = tmp_path / "code-ran"
    run = tmp_path / "evil"
    run.mkdir()
    write_run_json(run, {"status": "done", "config": {}})
    torch.save({"model": RunsCode(marker), "levels": []}, run / "model.pt")
    with pytest.raises(RunError, match=r"model\.pt: cannot load"):
        load_run(run)
    (run / "checkpoints").mkdir()
    torch.save({"iteration": RunsCode(marker)}, run / "checkpoints" / "ckpt_000001.pt")
    with pytest.raises(Exception, match="(?i)weights_only|unpickl"):
        load_torch(run / "checkpoints" / "ckpt_000001.pt")
    assert not marker.exists(), "loading a run folder ran code from its pickle"


def test_no_training_setting_names_a_path():
    from kgs_core.train.settings import parse_setting, schema

    assert "init_from" not in schema()
    with pytest.raises(ValueError, match="not KEY=VALUE with KEY a training setting"):
        parse_setting("init_from=/tmp/evil")
    # No free-text setting is left: every word a setting takes is one of its choices.
    from kgs_core.train.settings import setting_type

    assert not [k for k in schema() if setting_type(k) is str]


@pytest.mark.parametrize(
    "text",
    [
        "lr_means=NaN",
        "model.tau=Infinity",
        "model.tau=0",
        "seed=-5",
        "iterations=99999999999",
        "init_points=2000000000",
        "batch_size=100000",
        "lod_fractions=[0.5, NaN]",
        "model.deform_spatial=100000",
        "exposure=-0.1",
        "densify.max_gaussians=1000000000",
        "lambda_reg=-1",
        "model.deform_multires=[1,2,3,4,5]",
    ],
)
def test_out_of_bounds_settings_are_refused_naming_the_key(text):
    from kgs_core.train.config import make_config
    from kgs_core.train.settings import parse_setting

    key = text.split("=")[0]
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        parse_setting(text)
    # make_config checks the same bounds, whichever way the value came.
    value = json.loads(text.split("=", 1)[1])
    with pytest.raises(ValueError, match=key.replace(".", r"\.")):
        make_config("fast", **{key: tuple(value) if isinstance(value, list) else value})


def test_every_preset_is_inside_the_bounds():
    from kgs_core.train.config import PRESETS, make_config

    for preset in PRESETS:
        make_config(preset)


@pytest.fixture(scope="module")
def synth_scene(tmp_path_factory):
    return synthesize("bounce", tmp_path_factory.mktemp("colmap") / "synth", blur="none", size=32, frames=4, subframes=1, progress=False)


@pytest.fixture(scope="module")
def colmap_scene(synth_scene, colmap_text):
    return colmap_text(synth_scene, synth_scene.parent / "c")


@pytest.mark.parametrize("name", ["../../outside.png", "ABSOLUTE", "../synth/sharp/0000.png"])
def test_colmap_image_names_cannot_leave_the_image_folder(colmap_scene, synth_scene, colmap_text, tmp_path, name):
    name = str(tmp_path / "outside.png") if name == "ABSOLUTE" else name
    colmap_text(synth_scene, tmp_path / "d" / "c", name)
    reached = (tmp_path / "d" / "c" / "images" / name).resolve()
    messages = []
    for exists in (True, False):  # the answer does not tell whether the file it names exists
        if exists:
            reached.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(next((colmap_scene / "images").iterdir()), reached)
        else:
            reached.unlink()
        with pytest.raises(SceneError, match="absolute path|leaves the dataset folder") as err:
            load_scene(tmp_path / "d" / "c")
        messages.append(str(err.value))
    assert messages[0] == messages[1]


def test_every_reader_s_files_are_checked_inside_the_folder(colmap_scene, tmp_path, monkeypatch):
    """A reader that forgets the path check (a fourth format) is still refused by load_scene."""
    from kgs_core.data import formats

    real = formats.load_colmap
    outside = tmp_path / "secret.png"
    shutil.copyfile(next((colmap_scene / "images").iterdir()), outside)

    def careless(root):
        scene = real(root)
        scene.frames[0].image_path = outside
        return scene

    monkeypatch.setattr(formats, "load_colmap", careless)
    with pytest.raises(SceneError, match="leaves the dataset folder"):
        load_scene(colmap_scene)


@pytest.mark.parametrize(
    "entry",
    [
        {"time": 0.5, "camera_id": None},
        {"time": [0.5]},
        {"time": float("nan")},
        {"time": "noon"},
        [0.5],
        {"camera_id": 0},
        {"time": 0.1, "split": 3},
        {"time": 0.1, "exposure": {}},
    ],
)
def test_hostile_colmap_times_name_the_file(colmap_scene, tmp_path, entry):
    root = tmp_path / "c"
    shutil.copytree(colmap_scene, root)
    times = json.loads((root / "times.json").read_text())
    times[next(iter(times))] = entry
    (root / "times.json").write_text(json.dumps(times).replace("NaN", "NaN"))
    with pytest.raises(SceneError, match="times.json"):
        load_scene(root)


@pytest.mark.parametrize("content", ["[]", "3", "null", "[1, 2]"])
def test_whole_times_json_or_kgs_json_of_the_wrong_kind(colmap_scene, tmp_path, content):
    for name in ("times.json", "kgs.json"):
        root = tmp_path / name / "c"
        shutil.copytree(colmap_scene, root)
        (root / name).write_text(content)
        with pytest.raises(SceneError, match=name.replace(".", r"\.")):
            load_scene(root)


def test_the_colmap_reader_still_reads_its_own_writing(colmap_scene):
    scene = load_scene(colmap_scene, normalize=False)
    assert len(scene.frames) >= 4 and all(f.image_path.is_file() for f in scene.frames)
    assert np.isfinite([f.time for f in scene.frames]).all()
