"""Numerical stability on stiff and extreme inputs (issue: numerical stability). Property-based
(hypothesis) against float64 references: the kinematic basis, covariance refinement, the
rotation exp map, quaternions, projection of degenerate Gaussians, SH, activations, compositing
under transmittance underflow; the reference-axis switch; the NaN/Inf guards of training."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from kgs_core.model.kinematics import kinematic_basis, motion_blur_covariance, refine_covariance, so3_exp
from kgs_core.render import rasterize
from kgs_core.render.camera import intrinsics, look_at
from kgs_core.render.covariance import pack_covariance, quat_to_rotmat, unpack_covariance
from kgs_core.render.sh import sh_basis

BASES = ("paper", "duff", "principal")
f64 = torch.float64


def unit(seed: int, n: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    v = torch.randn(n, 3, generator=g, dtype=f64)
    return v / v.norm(dim=-1, keepdim=True)


def spd(seed: int, n: int = 1, scale: float = 1.0, aniso: float = 10.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g, dtype=f64)
    s = scale * torch.exp(torch.rand(n, 3, generator=g, dtype=f64) * math.log(aniso))
    M = quat_to_rotmat(q) * s[:, None, :]
    return M @ M.transpose(-1, -2)


magnitudes = st.sampled_from([0.0, 1e-12, 1e-6, 1e-3, 1.0, 1e3, 1e6])


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10**6), mag=magnitudes, basis=st.sampled_from(BASES), along_x=st.sampled_from([0, 1, -1]))
def test_kinematic_basis_orthonormal_and_finite(seed, mag, basis, along_x):
    d = unit(seed) if along_x == 0 else torch.tensor([[float(along_x), 0.0, 0.0]], dtype=f64)
    v = (d * mag).requires_grad_(True)
    sigma = spd(seed)
    R = kinematic_basis(v, basis, sigma)
    assert torch.isfinite(R).all()
    (R * torch.randn_like(R)).sum().backward()
    assert torch.isfinite(v.grad).all()
    if mag >= 1e-6:  # below ~1e-9 the frame degenerates by design; refine_covariance blends it away
        tol = max(1e-9, 4 * (1e-9 / mag) ** 2)  # |u_z| = 1 - EPS_DIR^2 / (2 |v|^2)
        RtR = R[0].T @ R[0]
        assert torch.allclose(RtR, torch.eye(3, dtype=f64), atol=tol)
        assert abs(torch.linalg.det(R[0]).item() - 1) < tol
        assert torch.allclose(R[0, :, 2], d[0], atol=tol)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 10**6),
    mag=magnitudes,
    basis=st.sampled_from(BASES),
    sigma_scale=st.sampled_from([1e-30, 1e-12, 1e-4, 1.0, 1e4]),
    blur=st.sampled_from([0.0, 1e-3, 1.0, 100.0]),
)
def test_refined_covariance_spd_with_finite_gradients(seed, mag, basis, sigma_scale, blur):
    n = 4
    v = (unit(seed, n) * mag).requires_grad_(True)
    sigma = spd(seed, n, sigma_scale).requires_grad_(True)
    ds = (0.5 * torch.randn(n, 3, dtype=f64)).requires_grad_(True)
    dr = (0.5 * torch.randn(n, 3, dtype=f64)).requires_grad_(True)
    kappa = torch.tensor(-2.0, dtype=f64, requires_grad=True)
    speed = v.norm(dim=-1)
    rz = unit(seed + 1, n)
    out = refine_covariance(sigma, v, speed * blur, ds, dr, rz, kappa, speed * 0.02, basis=basis)
    assert torch.isfinite(out).all()
    assert torch.allclose(out, out.transpose(-1, -2), rtol=1e-10, atol=1e-300)
    evals = torch.linalg.eigvalsh(out)
    assert (evals >= -1e-9 * evals.abs().max(-1, keepdim=True).values).all()  # PSD up to round-off
    assert (torch.diagonal(out, dim1=-2, dim2=-1) > 0).all()  # positive scales even as sigma -> 0
    (out * torch.randn_like(out)).sum().backward()
    for t in (v, sigma, ds, dr, kappa):
        assert torch.isfinite(t.grad).all()


def test_motion_blur_covariance_is_the_second_moment_of_the_moving_gaussian():
    # Samples of a Gaussian swept uniformly along v for the exposure: their covariance is what
    # the convolve form of K.R. predicts (within sampling error).
    g = torch.Generator().manual_seed(3)
    sigma = spd(5, 1, 0.1)
    v = torch.tensor([[0.8, -0.3, 0.5]], dtype=f64)
    exposure_time = 0.7
    n = 400_000
    L = torch.linalg.cholesky(sigma[0])
    pts = torch.randn(n, 3, generator=g, dtype=f64) @ L.T + torch.rand(n, 1, generator=g, dtype=f64) * exposure_time * v
    empirical = torch.cov(pts.T)
    predicted = unpack_covariance(motion_blur_covariance(pack_covariance(sigma), v * exposure_time))[0]
    assert torch.allclose(empirical, predicted, atol=3e-3 * predicted.abs().max().item())
    cov6 = pack_covariance(sigma)
    assert torch.equal(motion_blur_covariance(cov6, v * 0.0), cov6)  # sharp render: untouched


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 10**6),
    mag=magnitudes,
    sigma_scale=st.sampled_from([1e-30, 1e-12, 1e-4, 1.0, 1e4]),
    exposure=st.sampled_from([0.0, 1e-3, 1.0, 100.0]),
)
def test_motion_blur_covariance_spd_with_finite_gradients(seed, mag, sigma_scale, exposure):
    n = 4
    v = (unit(seed, n) * mag).requires_grad_(True)
    sigma = spd(seed, n, sigma_scale).requires_grad_(True)
    out = unpack_covariance(motion_blur_covariance(pack_covariance(sigma), v * exposure))
    assert torch.isfinite(out).all()
    assert torch.allclose(out, out.transpose(-1, -2), rtol=0, atol=0)
    evals = torch.linalg.eigvalsh(out)
    assert (evals >= -1e-9 * evals.abs().max(-1, keepdim=True).values).all()
    (out * torch.randn_like(out)).sum().backward()
    assert torch.isfinite(v.grad).all() and torch.isfinite(sigma.grad).all()


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10**6), log_angle=st.floats(-12, 0), near_pi=st.booleans())
def test_so3_exp_matches_float64_reference(seed, log_angle, near_pi):
    axis = unit(seed)[0].numpy()
    angle = math.pi - 10**log_angle if near_pi else 10**log_angle
    w = torch.tensor(axis * angle, dtype=torch.float32)[None]
    R = so3_exp(w)[0].double().numpy()
    ref = Rotation.from_rotvec(axis * angle).as_matrix()
    assert np.abs(R - ref).max() < 2e-6
    assert abs(np.linalg.det(R) - 1) < 1e-5


def test_so3_exp_gradient_finite_at_zero():
    w = torch.zeros(3, 3, dtype=f64, requires_grad=True)
    so3_exp(w).sum().backward()
    assert torch.isfinite(w.grad).all()
    torch.autograd.gradcheck(so3_exp, (torch.full((2, 3), 1e-5, dtype=f64, requires_grad=True),))


def test_zero_quaternion_is_identity_with_finite_gradient():
    q = torch.zeros(2, 4, dtype=f64, requires_grad=True)
    R = quat_to_rotmat(q)
    assert torch.equal(R, torch.eye(3, dtype=f64).expand(2, 3, 3))
    R.sum().backward()
    assert torch.isfinite(q.grad).all()


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10**6), degree=st.integers(0, 3), axis=st.sampled_from([None, 0, 1, 2]))
def test_sh_basis_float32_matches_float64(seed, degree, axis):
    d = unit(seed, 16)
    if axis is not None:
        d = torch.zeros(16, 3, dtype=f64)
        d[:, axis] = 1.0
    ref = sh_basis(d, degree)
    got = sh_basis(d.float(), degree).double()
    assert torch.isfinite(got).all() and (got - ref).abs().max() < 1e-6


def test_activations_at_extreme_logits():
    from kgs_core.model.config import ModelConfig
    from kgs_core.model.dynamic import KinematicsGS
    from kgs_core.model.gaussians import init_from_points

    p = init_from_points(np.zeros((4, 3)), np.full((4, 3), 0.5), 1, 4)
    p.opacity_logits = torch.tensor([-1e4, -88.0, 88.0, 1e4]).requires_grad_(True)
    p.log_scales = torch.tensor([[-1e4] * 3, [-50.0] * 3, [50.0] * 3, [1e4] * 3]).requires_grad_(True)
    m = KinematicsGS(p, ModelConfig())
    o, s = p.opacities, m.scales()
    assert torch.isfinite(o).all() and (o >= 0).all() and (o <= 1).all()
    assert torch.isfinite(s).all() and (s > 0).all()
    (o.sum() + s.sum()).backward()
    assert torch.isfinite(p.opacity_logits.grad).all() and torch.isfinite(p.log_scales.grad).all()


def _render(means, covars, opac, backend, w=32, h=32):
    viewmat = look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0))
    K = intrinsics(w, h, 60.0)
    colors = torch.rand(len(means), 3, generator=torch.Generator().manual_seed(0))
    return rasterize(means, opac, viewmat, K, w, h, covars=covars, colors=colors, backend=backend)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("case", ["needle", "disc", "near_plane", "behind", "far_off_screen", "huge", "underflow"])
def test_projection_and_compositing_extremes(case, backend, ext):
    n = 200 if case == "underflow" else 8
    g = torch.Generator().manual_seed(1)
    means = 0.2 * torch.randn(n, 3, generator=g)
    scales = torch.full((n, 3), 0.05)
    opac = torch.full((n,), 0.5)
    if case == "needle":
        scales = torch.tensor([[1e-7, 1e-7, 1.0]]).expand(n, 3).clone()
    elif case == "disc":
        scales = torch.tensor([[1.0, 1.0, 1e-8]]).expand(n, 3).clone()
    elif case == "near_plane":
        means[:, 2] = -3.0 + 0.01 + 1e-6  # at the near plane of the camera at z = -3
    elif case == "behind":
        means[:, 2] = -5.0
    elif case == "far_off_screen":
        means[:, 0] = 1e6
    elif case == "huge":
        scales = torch.full((n, 3), 1e4)
    elif case == "underflow":  # a stack of opaque Gaussians: T underflows long before the last
        means = torch.zeros(n, 3) + torch.linspace(-1, 1, n)[:, None] * torch.tensor([0.0, 0.0, 1.0])
        opac = torch.full((n,), 0.99)
    q = quat_to_rotmat(torch.randn(n, 4, generator=g))
    covars = (q * scales[:, None, :]) @ (q * scales[:, None, :]).transpose(-1, -2)
    means.requires_grad_(True)
    covars.requires_grad_(True)
    opac.requires_grad_(True)
    out = _render(means, covars, opac, backend)
    assert torch.isfinite(out.image).all() and torch.isfinite(out.alpha).all()
    assert (out.alpha >= 0).all() and (out.alpha <= 1 + 1e-6).all()
    (out.image.sum() + out.alpha.sum()).backward()
    for t in (means, covars, opac):
        assert torch.isfinite(t.grad).all(), case


def jump_across_switch(basis: str, seed: int = 0, delta: float = 1e-7) -> float:
    """Largest relative change of Sigma_kin over a step of 2e-7 in u_z . e_x across 0.99 (the
    paper's reference-axis switch), over 20 random anisotropic covariances."""

    def direction(x):  # |u_z . e_x| = x, the rest split between y and z
        r = math.sqrt(1 - x * x) / math.sqrt(2)
        return [x, r, r]

    vs = torch.tensor([direction(0.99 - delta), direction(0.99 + delta)], dtype=f64)
    worst = 0.0
    for k in range(20):
        sigma = spd(seed + k, 1, 0.01, 20.0).expand(2, 3, 3)
        z = torch.zeros(2, 3, dtype=f64)
        rz = unit(seed + k).expand(2, 3)
        out = refine_covariance(
            sigma,
            vs,
            torch.full((2,), 0.05, dtype=f64),
            z,
            z,
            rz,
            torch.tensor(-2.0, dtype=f64),
            torch.full((2,), 1.0, dtype=f64),
            basis=basis,
        )
        worst = max(worst, ((out[1] - out[0]).norm() / out[0].norm()).item())
    return worst


def test_reference_axis_switch_jumps_and_principal_basis_does_not():
    assert jump_across_switch("paper") > 1e-2
    assert jump_across_switch("principal") < 1e-5


@pytest.fixture
def tiny_scene(tmp_path):
    from kgs_core.data.formats import load_scene
    from kgs_core.data.synth.generate import synthesize

    return load_scene(synthesize("bounce", tmp_path / "s", blur="mild", size=24, frames=6, subframes=2, progress=False))


def _cfg(**over):
    from kgs_core.train.config import make_config

    base = {
        "iterations": 30,
        "eval_every": 10,
        "checkpoint_every": 10,
        "decompose_at": 10,
        "decompose_every": 0,
        "lod_levels": 1,
        "lod_fractions": (1.0,),
        "init_points": 300,
        "densify.start": 1000,
        "densify.opacity_reset_at": (),
        "densify.max_gaussians": 1000,
    }
    base.update(over)
    return make_config("fast", **base)


def _poison_at(trainer, iteration: int, tensor=lambda tr: tr.model.params.means):
    """Makes the gradient of `tensor(trainer)` (default the Gaussian means) NaN once, at `iteration`."""
    hit = {"done": False}
    orig = trainer.check_gradients

    def check(it):
        if it == iteration and not hit["done"]:
            hit["done"] = True
            grad = tensor(trainer).grad
            grad.view(-1)[0] = float("nan")
        orig(it)

    trainer.check_gradients = check


def test_nonfinite_gradient_error_names_tensor_and_iteration(tiny_scene, tmp_path):
    from kgs_core.train.trainer import NonFiniteError, Trainer

    tr = Trainer(tiny_scene, tmp_path / "run", _cfg(), progress=False)
    _poison_at(tr, 17)
    with pytest.raises(NonFiniteError, match=r"gaussians\.means .* at iteration 17"):
        tr.run()
    assert "NonFiniteError" in (tmp_path / "run" / "error.txt").read_text()


@pytest.mark.parametrize(
    "name,settings,tensor",
    [
        ("camera_motion.motion", {"camera_blur": "learned"}, lambda tr: tr.camera_motion.motion),
        ("pose_correction.delta", {"pose_refine": True}, lambda tr: tr.pose_correction.delta),
        ("exposure.logit", {"fit_exposure": True, "exposure": 0.5}, lambda tr: tr.fitted_exposure.logit),
    ],
)
def test_nonfinite_gradient_of_the_camera_and_exposure_parameters_is_named(tiny_scene, tmp_path, name, settings, tensor):
    """Not only the Gaussians and the field: every fitted parameter is checked (the exposure
    and the learned camera motion act after the decomposition at iteration 10)."""
    from kgs_core.train.trainer import NonFiniteError, Trainer

    tr = Trainer(tiny_scene, tmp_path / "run", _cfg(**settings, **{"model.tau": 1e-9}), progress=False)
    _poison_at(tr, 17, tensor)
    with pytest.raises(NonFiniteError, match=rf"{name} .* at iteration 17"):
        tr.run()


def test_nonfinite_restore_continues_with_lower_learning_rate(tiny_scene, tmp_path):
    import json

    from kgs_core.train.trainer import Trainer

    tr = Trainer(tiny_scene, tmp_path / "run", _cfg(on_nonfinite="restore"), progress=False)
    _poison_at(tr, 17)
    info = tr.run()
    assert info["status"] == "done" and info["iteration"] == 30
    events = json.loads((tmp_path / "run" / "run.json").read_text())["guard_events"]
    assert events[0]["event"] == "restored" and events[0]["iteration"] == 10 and events[0]["lr_scale"] == 0.5
    assert "iteration 17" in events[0]["reason"]
    assert all(torch.isfinite(v).all() for v in tr.model.params.items() for v in [v[1]])


@pytest.mark.parametrize("basis", BASES)
def test_still_gaussians_blend_to_the_predicted_covariance_with_bounded_gradient(basis):
    """v -> 0: the velocity direction is noise, so Sigma_kin fades into the predicted Sigma:
    exactly `(1 - w) Sigma + w Sigma_kin(direction)` with `w = (|v| dt)^2 / ((|v| dt)^2 + still^2)`,
    at every speed, and the gradient stays bounded."""
    sigma = spd(3, 1, 0.05, 10.0)
    d = unit(4)
    still = 1e-3
    z = torch.zeros(1, 3, dtype=f64)
    kappa = torch.tensor(-2.0, dtype=f64)
    # Sigma_kin of this direction without any fade (no blur, no residuals: the projection onto the
    # kinematic frame), which must differ from Sigma for the blend to show.
    kin = refine_covariance(
        sigma, d, torch.zeros(1, dtype=f64), z, z, unit(5), kappa, torch.tensor([1e9], dtype=f64), basis=basis, still_len=still
    )
    assert (kin - sigma).norm() > 1e-3 * sigma.norm()
    worst_grad = 0.0
    for mag in [0.0, 1e-9, 1e-7, 1e-5, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2]:
        v = (d * mag).requires_grad_(True)
        out = refine_covariance(sigma, v, torch.zeros(1, dtype=f64), z, z, unit(5), kappa, v.norm(dim=-1), basis=basis, still_len=still)
        w = mag**2 / (mag**2 + still**2)
        # (below |v| ~ 1e-9 the direction is shortened by the normalisation guard, but w ~ 1e-12 there)
        assert torch.allclose(out, (1 - w) * sigma + w * kin, rtol=0, atol=1e-9 * sigma.norm().item()), mag
        out.sum().backward()
        worst_grad = max(worst_grad, v.grad.norm().item())
    assert worst_grad < 10.0 / still * sigma.norm().item()


def test_convolve_form_is_sharp_at_zero_exposure_and_elongates_along_the_motion():
    """`kr_form = convolve`: at exposure 0 a dynamic Gaussian's covariance is the D3DGS-style
    residual covariance exactly (what `--ablate kr` renders); at exposure e it gains
    `(|v| dt e)^2 / 12` along its velocity and nothing across it."""
    from dataclasses import replace

    from kgs_core.model.config import ModelConfig
    from kgs_core.model.dynamic import KinematicsGS
    from kgs_core.model.gaussians import init_from_points

    g = torch.Generator().manual_seed(0)
    p = init_from_points((0.3 * torch.randn(64, 3, generator=g)).numpy(), np.full((64, 3), 0.5), 1, 4)
    torch.manual_seed(0)
    cfg = ModelConfig(kr_form="convolve", feature_dim=4, deform_spatial=8, deform_temporal=4, deform_features=4, deform_multires=(1,))
    m = KinematicsGS(p, cfg)
    with torch.no_grad():  # a field that moves things: random last layers
        for mlp in (m.deform.mlp, m.fine.mlp):
            mlp[-1].weight.normal_(0, 0.3)
        for grid in m.deform.planes.grids:
            grid.add_(0.2 * torch.randn(grid.shape, generator=g))
    m.decompose(tau=0.0)
    m.dynamic[:] = True  # every Gaussian takes the dynamic path, whatever its K
    sharp = m.at(0.4, exposure=0.0, dt=0.05)
    ref = KinematicsGS(p, replace(cfg, kinematic=False))
    ref.load_state_dict(m.state_dict())
    ref.decomposed, ref.dynamic = True, m.dynamic.clone()
    assert torch.allclose(sharp.covars, ref.at(0.4, exposure=0.0, dt=0.05).covars, rtol=1e-6, atol=1e-9)
    # A long frame interval, so that the sweep is not lost in the covariance's float32 round-off
    # (the sharp covariance does not depend on it).
    blurred = m.at(0.4, exposure=0.8, dt=0.5)
    v = blurred.velocity
    assert (v.norm(dim=-1) > 0).all()
    u = v / v.norm(dim=-1, keepdim=True)
    gain = torch.einsum("ni,nij,nj->n", u, blurred.covars - sharp.covars, u)
    # (float32 round-off of the covariance along u bounds how well a small gain is resolved)
    along = torch.einsum("ni,nij,nj->n", u, sharp.covars, u)
    expected = (v.norm(dim=-1) * 0.5 * 0.8) ** 2 / 12
    assert ((gain - expected).abs() <= 1e-4 * expected + 1e-6 * along).all()
    assert (expected > 1e-4 * along).any()  # some gains are 100x above that round-off bound
    w = torch.linalg.cross(u, torch.randn(64, 3, generator=g))  # any direction across the motion
    across = torch.einsum("ni,nij,nj->n", w, blurred.covars - sharp.covars, w)
    assert (across.abs() <= 1e-6 * torch.einsum("ni,nij,nj->n", w, sharp.covars, w)).all()  # float32 round-off


def test_camera_motion_from_poses_matches_the_projected_motion_of_still_points():
    """`(A, b)` from three poses: a still point's motion relative to the camera, expressed in
    the world frame, is `A x + b` (finite difference of its camera coordinates)."""
    from kgs_core.data.synth.scenes import shaky_training_camera
    from kgs_core.train.camera_motion import camera_motion_from_poses

    cam = shaky_training_camera(0)
    t, h = 0.4, 1e-5
    A, b = camera_motion_from_poses(cam(t - h), cam(t), cam(t + h), t - h, t + h)
    g = np.random.default_rng(0)
    for x in g.uniform(-1, 1, size=(5, 3)):
        W0, W1, Wm = cam(t + h), cam(t - h), cam(t)
        dp = ((W0[:3, :3] @ x + W0[:3, 3]) - (W1[:3, :3] @ x + W1[:3, 3])) / (2 * h)
        expected = Wm[:3, :3].T @ dp
        got = A.double().numpy() @ x + b.double().numpy()
        assert np.allclose(got, expected, rtol=1e-4, atol=1e-4 * np.abs(expected).max())


def test_camera_blur_elongates_still_gaussians_along_the_camera_motion():
    from kgs_core.model.config import ModelConfig
    from kgs_core.model.dynamic import KinematicsGS
    from kgs_core.model.gaussians import init_from_points

    g = torch.Generator().manual_seed(1)
    p = init_from_points((0.3 * torch.randn(32, 3, generator=g)).numpy(), np.full((32, 3), 0.5), 1, 16)
    m = KinematicsGS(p, ModelConfig())
    m.decompose(tau=1.0)  # a fresh field: everything static
    assert not m.dynamic.any()
    A, b = 0.5 * torch.randn(3, 3, generator=g), torch.randn(3, generator=g)
    sharp = m.at(0.5, exposure=1.0, dt=0.1)  # without camera motion static Gaussians stay sharp
    blurred = m.at(0.5, exposure=1.0, dt=0.1, camera_motion=(A, b))
    assert torch.equal(sharp.covars, m.at(0.5, exposure=0.0, dt=0.1, camera_motion=(A, b)).covars)
    u = p.means.detach() @ A.T + b
    expected = sharp.covars + (0.1**2 / 12) * u[:, :, None] * u[:, None, :]
    assert torch.allclose(blurred.covars, expected, rtol=1e-5, atol=1e-9)


def test_the_stability_bench_trains_with_the_tau_it_is_given(tmp_path):
    """`bench stability --tau` runs the kinematic path on (nearly) every Gaussian: the given τ is
    the threshold itself, not a floor under Otsu's automatic split, which would still cut K in two."""
    from app.bench.stability import train_case

    row = train_case("5 fps (10 frames)", tmp_path, iterations=60, size=24, tau=1e-12)
    assert row["finite"] and row["dynamic_share"] > 0.95
