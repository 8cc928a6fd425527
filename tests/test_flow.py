"""The optical-flow term (kgs_core/train/flow.py): its residual and the flows it reads."""

from __future__ import annotations

import numpy as np
import pytest
import torch


def test_flow_residual_is_the_image_motion_minus_the_flow_for_visible_gaussians_only():
    """Points moving 0.1 units across at depth 2 (f = 100 px: 5 px in the image) against a flow
    of (8, 0) px: a residual of (-3, 0) each; a point behind the rendered depth and one outside
    the image are left out; the gradient moves the next positions along the flow."""
    from kgs_core.train.flow import charbonnier, flow_residual

    K = torch.tensor([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])
    cam = (torch.eye(4), K)
    x_t = torch.tensor([[0.0, 0.0, 2.0], [0.1, -0.1, 2.0], [0.0, 0.1, 3.0], [5.0, 0.0, 2.0]])
    x_next = (x_t + torch.tensor([0.1, 0.0, 0.0])).requires_grad_(True)
    flow = torch.zeros(64, 64, 2)
    flow[..., 0] = 8.0
    depth = torch.full((64, 64, 1), 2.0)  # the third point (depth 3) is hidden; the fourth is at u = 282
    r = flow_residual(x_t, x_next, cam, cam, flow, depth)
    assert r.shape == (2, 2) and torch.allclose(r, torch.tensor([[-3.0, 0.0], [-3.0, 0.0]]), atol=1e-4)
    charbonnier(r).backward()
    assert (x_next.grad[:2, 0] < 0).all()  # descending the loss moves them further along +u
    assert torch.all(x_next.grad[2:] == 0)


def test_forward_backward_check_keeps_flow_the_way_back_confirms():
    """A 3 px shift confirmed by a -3 px flow back is kept, except in the last 3 columns (they
    point outside the image); where the way back says +3 px (an occlusion) it is dropped; a
    NaN flow leaves its Gaussian out of the residual."""
    import numpy as np

    from kgs_core.train.flow import consistent, flow_residual

    H, W = 20, 30
    fwd = np.zeros((H, W, 2), np.float32)
    fwd[..., 0] = 3.0
    ok = consistent(fwd, -fwd)
    assert ok[:, : W - 3].all() and not ok[:, W - 2 :].any()
    bad = -fwd.copy()
    bad[10:, ..., 0] = 3.0
    ok = consistent(fwd, bad)
    assert ok[:8, : W - 3].all() and not ok[11:].any()

    K = torch.tensor([[100.0, 0, 15], [0, 100.0, 10], [0, 0, 1]])
    cam = (torch.eye(4), K)
    x_t = torch.tensor([[0.0, -0.05, 2.0], [0.0, 0.05, 2.0]])  # rows 7.5 and 12.5
    flow = torch.from_numpy(fwd.copy())
    flow[11:] = float("nan")
    r = flow_residual(x_t, x_t, cam, cam, flow, torch.full((H, W, 1), 2.0))
    assert r.shape == (1, 2) and torch.allclose(r, torch.tensor([[-3.0, 0.0]]))


def test_frame_flows_pair_each_frame_with_the_next_of_its_camera_and_measure_the_shift():
    """Three frames of one camera (out of time order in the list) and one of another: flows go
    from each to the next of its own camera in time, and a texture shifted by 3 px comes out as
    a 3 px flow."""
    import types

    import numpy as np
    from scipy import ndimage

    from kgs_core.train.flow import frame_flows

    rng = np.random.default_rng(0)
    base = ndimage.gaussian_filter(rng.random((72, 96)), 1.5)
    base = (base - base.min()) / (base.max() - base.min())

    def frame(fid, time, shift, camera_id=0):
        img = np.roll(base, shift, axis=1)
        return types.SimpleNamespace(id=fid, time=time, camera_id=camera_id, image=lambda img=img: np.stack([img] * 3, -1))

    frames = [frame("b", 0.5, 3), frame("a", 0.0, 0), frame("c", 1.0, 6), frame("other", 0.2, 0, camera_id=1)]
    flows = frame_flows(frames)
    assert set(flows) == {"a", "b"} and flows["a"][0] == 0 and flows["b"][0] == 2
    inner = flows["a"][1][12:-12, 12:-12]
    assert abs(float(inner[..., 0].median()) - 3.0) < 0.3 and abs(float(inner[..., 1].median())) < 0.3


def patch_over_background(seed: int, pan: int, move: int) -> list:
    """Two grey frames (as training frames of one camera): a 16 px texture at column 50, then
    `move` px to the right, over a background texture that moves `pan` px to the left."""
    import types

    from scipy import ndimage

    rng = np.random.default_rng(seed)

    def texture(h, w, sigma):
        t = ndimage.gaussian_filter(rng.random((h, w)), sigma)
        return (t - t.min()) / (t.max() - t.min())

    background, patch = texture(96, 148, 1.5), texture(16, 16, 0.8)

    def frame(fid, time, pan, x):
        img = background[:, 10 + pan : 138 + pan].copy()
        img[40:56, x : x + 16] = patch
        return types.SimpleNamespace(id=fid, time=time, camera_id=0, image=lambda img=img: np.stack([img] * 3, -1))

    return [frame("a", 0.0, 0, 50), frame("b", 1.0, pan, 50 + move)]


def test_frame_flows_follow_a_small_object_moving_against_the_background():
    """A 16 px textured patch moving +5 px while the background moves -1 px (a toy car crossing
    a panning shot): with `method="fused"` the flow inside the patch is its own motion, not the
    background's (DIS alone gives it the background's -0.8 px), and the background keeps its
    -1 px; an unknown method is refused by name."""
    from kgs_core.train.flow import frame_flows

    frames = patch_over_background(0, pan=1, move=5)
    with pytest.raises(ValueError, match="flow method"):
        frame_flows(frames, method="farneback")
    flow = frame_flows(frames, method="fused")["a"][1]
    inside = flow[44:52, 54:62].reshape(-1, 2)
    inside = inside[torch.isfinite(inside).all(-1)]
    assert len(inside) > 32
    assert abs(float(inside[:, 0].median()) - 5.0) < 0.5 and abs(float(inside[:, 1].median())) < 0.5
    sky = flow[:30, 8:-8].reshape(-1, 2)
    sky = sky[torch.isfinite(sky).all(-1)]
    assert abs(float(sky[:, 0].median()) + 1.0) < 0.2


@pytest.mark.parametrize("method", ["dis_full", "fused"])
def test_the_splits_flow_measures_a_small_objects_own_motion(method):
    """A 16 px textured patch moving 3 px while the background moves 1 px the other way, over
    four random textures: at full resolution ("dis_full") and fused, where the
    forward-backward check keeps the patch's flow (three textures of four at least) it is the
    patch's 3 px; DIS's preset, which stops at half resolution, gives it 2.2-2.4 px."""
    from kgs_core.train.flow import frame_flows

    kept = 0
    for seed in range(4):
        flow = frame_flows(patch_over_background(seed, pan=1, move=3), method=method)["a"][1]
        inside = flow[44:52, 54:62, 0].reshape(-1)
        inside = inside[torch.isfinite(inside)]
        if len(inside) > 32:
            kept += 1
            assert abs(float(inside.median()) - 3.0) < 0.3, seed
    assert kept >= 3


def test_trainer_flow_term_reaches_the_field_and_trains_with_pose_refinement(tmp_path):
    """`lambda_flow` > 0: a flow for every training frame but the last, a finite positive term
    whose gradient reaches the deformation field, and a short training (with refined poses,
    whose corrections the term applies to both times) that stays finite."""
    from kgs_core.data.formats import load_scene
    from kgs_core.data.synth.generate import synthesize
    from kgs_core.model.render import render_model
    from kgs_core.train.config import make_config
    from kgs_core.train.trainer import Trainer

    scene = load_scene(
        synthesize("sheet", tmp_path / "s", blur="mild", size=40, frames=6, subframes=2, seed=0, progress=False, overwrite=True)
    )
    cfg = make_config("fast", iterations=40)
    cfg.lambda_flow, cfg.pose_refine = 0.01, True
    tr = Trainer(scene, tmp_path / "r", cfg, progress=False)
    assert set(tr.flows) == {f.id for f in scene.train_frames[:-1]}
    tr.init_model()
    frame = scene.train_frames[0]
    out, g = render_model(tr.model, frame.camera, frame.time, 0.0, scene.dt)
    term = tr.flow_term(frame, out, g)
    assert torch.isfinite(term) and term > 0
    term.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in tr.model.deform.parameters())
    tr.model.zero_grad(set_to_none=True)
    info = tr.run()
    assert info["iteration"] == 40 and torch.isfinite(torch.tensor(info["final_psnr_heldout"]))
    # After a decomposition (here one that calls every Gaussian dynamic: 40 steps of a 40 px scene move
    # too little for τ), with an exposure, the term reads K.R.'s velocity with its gradient.
    tr.model.decompose(tau=-1.0, recompute=False)
    out, g = render_model(tr.model, frame.camera, frame.time, 0.5, scene.dt)
    assert tr.model.decomposed and g.dynamic.any() and "dynamic_velocity" in g.extras
    tr.model.zero_grad(set_to_none=True)
    term = tr.flow_term(frame, out, g)
    assert torch.isfinite(term)
    term.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in tr.model.deform.parameters())


def test_without_kr_velocity_the_flow_term_moves_own_line_gaussians_by_their_own_velocity(tmp_path):
    """Where K.R. computes no velocity (before the decomposition, or after its mid-run check turned it
    off) a training render hands the flow term no velocity, and the term evaluates the field no
    second time: a Gaussian on its own line moves by its `own_velocity` (changing it changes
    the term), every other one is read as standing still (changing where the field would put
    it next does not)."""
    from kgs_core.data.formats import load_scene
    from kgs_core.data.synth.generate import synthesize
    from kgs_core.model.render import render_model
    from kgs_core.train.config import make_config
    from kgs_core.train.trainer import Trainer

    scene = load_scene(
        synthesize("sheet", tmp_path / "s", blur="mild", size=40, frames=6, subframes=2, seed=0, progress=False, overwrite=True)
    )
    cfg = make_config("fast", iterations=30)
    cfg.lambda_flow = 0.01
    tr = Trainer(scene, tmp_path / "r", cfg, progress=False)
    tr.init_model()
    model, frame = tr.model, scene.train_frames[0]

    def term() -> float:
        out, g = render_model(model, frame.camera, frame.time, 0.5, scene.dt, velocity=False)
        assert g.dynamic.any() and "dynamic_velocity" not in g.extras
        return float(tr.flow_term(frame, out, g))

    def field_elsewhere(idx, t, noise=0.0):
        raise AssertionError("the flow term evaluated the field a second time")

    with torch.no_grad():
        model.positions = field_elsewhere
        try:
            before_split = term()
            model.decompose(tau=-1.0, recompute=False)
            model.config.kinematic = False  # what K.R.'s mid-run check does
            own = torch.arange(len(model)) % 2 == 0
            model.lifespan[own] = torch.tensor([frame.time, 1.0])
            model.own_velocity[own] = 0.0
            still = term()
            model.own_velocity[own] = torch.tensor([0.3, 0.0, 0.0])
            moving = term()
        finally:
            del model.positions
    assert np.isfinite(before_split) and before_split > 0
    assert abs(moving - still) > 1e-3 * still, (still, moving)


def test_unproject_inverts_project():
    from kgs_core.render import intrinsics, look_at
    from kgs_core.train.flow import project, unproject

    viewmat, K = look_at((0.3, -0.2, -2.0), (0.0, 0.1, 0.0)), intrinsics(80, 60)
    x = torch.randn(50, 3, generator=torch.Generator().manual_seed(0)) * 0.5
    uv, z = project(x, viewmat, K)
    assert torch.allclose(unproject(uv, z, viewmat, K), x, atol=1e-5)
