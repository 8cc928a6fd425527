"""The exposure learned from the footage (`TrainConfig.fit_exposure`, train/exposure.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from kgs_core.data.scene import Camera
from kgs_core.model.config import ModelConfig
from kgs_core.model.dynamic import KinematicsGS
from kgs_core.model.gaussians import init_from_points
from kgs_core.model.render import render_model
from kgs_core.train.exposure import FittedExposure


def still_scene_and_camera():
    """Small still Gaussians in front of a camera that moves sideways during the exposure:
    4.8 px of blur per unit of exposure, far above the splats' own size."""
    g = np.random.default_rng(0)
    pts = np.c_[g.uniform(-0.6, 0.6, (300, 2)), g.uniform(2.0, 3.0, 300)]
    p = init_from_points(pts, g.uniform(0, 1, (300, 3)), 0, 4)
    with torch.no_grad():
        p.log_scales.fill_(np.log(0.01))
        p.opacity_logits.fill_(2.0)
    model = KinematicsGS(
        p, ModelConfig(sh_degree=0, feature_dim=4, deform_spatial=8, deform_temporal=4, deform_features=4, deform_multires=(1,))
    )
    model.decompose(tau=1.0)  # a fresh field: every Gaussian static, blurred by the camera alone
    cam = Camera(K=np.array([[60.0, 0, 32], [0, 60.0, 32], [0, 0, 1]]), viewmat=np.eye(4), width=64, height=64)
    motion = (torch.zeros(3, 3), torch.tensor([2.0, 0.0, 0.0]))
    return model, cam, motion


@pytest.mark.parametrize("start,towards", [(0.3, "up"), (0.95, "down")])
def test_the_loss_pulls_the_exposure_towards_the_one_that_blurred_the_frame(start, towards):
    """Frames blurred at exposure 0.7: from a shorter start the photometric gradient lengthens
    the exposure, from a longer one it shortens it."""
    model, cam, motion = still_scene_and_camera()
    with torch.no_grad():
        target = render_model(model, cam, 0.5, 0.7, 0.1, camera_motion=motion)[0].image
    fitted = FittedExposure(start)
    out, _ = render_model(model, cam, 0.5, fitted.value(), 0.1, camera_motion=motion)
    (out.image - target).abs().mean().backward()
    grad = float(fitted.logit.grad)
    assert grad != 0.0 and np.isfinite(grad)
    assert (grad < 0) == (towards == "up"), grad  # gradient descent moves against the gradient


def test_fitted_exposure_starts_inside_its_range_and_round_trips():
    for start, expected in ((0.0, 0.05), (1.0, 0.95), (0.4, 0.4)):
        assert float(FittedExposure(start)) == pytest.approx(expected, rel=1e-6)
    a = FittedExposure(0.4)
    with torch.no_grad():
        a.logit.add_(0.7)
    b = FittedExposure(0.9)
    b.load_state_dict(a.state_dict())
    assert float(b) == float(a) and b.start == 0.4


def test_training_fits_the_exposure_and_records_the_choice(tmp_path):
    """The fitted exposure moves once K.R. acts (after the decomposition), is logged per evaluation,
    written to run.json with how it was chosen, and survives a resume."""
    import csv
    import json
    from pathlib import Path

    from kgs_core.data.formats import load_scene
    from kgs_core.train.config import make_config
    from kgs_core.train.trainer import Trainer

    walk = load_scene(Path(__file__).parent / "fixtures" / "walk96")
    # τ ~0 (a τ must be above 0): every Gaussian dynamic from the decomposition on, so that K.R. blurs (and the fit acts) at once.
    cfg = make_config(
        "fast",
        scene=walk,
        iterations=40,
        decompose_at=10,
        decompose_every=0,
        eval_every=20,
        checkpoint_every=20,
        fit_exposure=True,
        exposure=0.3,
        tau_auto=False,
        **{"model.tau": 1e-12},
    )
    t = Trainer(walk, tmp_path / "r", cfg, progress=False)
    info = t.run()
    assert info["exposure"] != pytest.approx(0.3, abs=1e-4) and 0 < info["exposure"] < 1
    assert info["exposure_choice"] == "fitted to the footage from 0.3"
    rows = list(csv.DictReader((tmp_path / "r" / "log.csv").open()))
    assert float(rows[0]["exposure"]) == pytest.approx(0.3) and float(rows[-1]["exposure"]) == pytest.approx(info["exposure"], abs=1e-5)
    assert json.loads((tmp_path / "r" / "run.json").read_text())["exposure"] == info["exposure"]
    # A resumed trainer reads the fitted value back from the checkpoint, not the start.
    again = Trainer(walk, tmp_path / "r", cfg, progress=False)
    again.restore(sorted((tmp_path / "r" / "checkpoints").glob("ckpt_*.pt"))[-1])
    assert again.exposure == pytest.approx(info["exposure"], abs=1e-6)
