"""The model's fast paths agree with the plain ones: the batched evaluation of the deformation
field at several times, the physical velocity built from it, and packed covariances from the
model to the rasteriser."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from kgs_core.model.config import ModelConfig
from kgs_core.model.deformation import Offsets
from kgs_core.model.dynamic import KinematicsGS
from kgs_core.model.gaussians import init_from_points
from kgs_core.render import intrinsics, look_at, packed_covariance, rasterize
from kgs_core.render.covariance import covariance_from_quat_scale, pack_covariance, unpack_covariance


def moving_model(n: int = 48, seed: int = 0, **config) -> KinematicsGS:
    """A small model whose field moves things (random last layers and planes), decomposed with
    every Gaussian dynamic."""
    g = torch.Generator().manual_seed(seed)
    p = init_from_points((0.3 * torch.randn(n, 3, generator=g)).numpy(), np.full((n, 3), 0.5), 1, 4).requires_grad_(True)
    torch.manual_seed(seed)
    m = KinematicsGS(
        p, ModelConfig(feature_dim=4, deform_spatial=8, deform_temporal=4, deform_features=4, deform_multires=(1, 2), **config)
    )
    with torch.no_grad():
        for mlp in (m.deform.mlp, m.fine.mlp):
            mlp[-1].weight.normal_(0, 0.3, generator=g)
        for grid in m.deform.planes.grids:
            grid.add_(0.2 * torch.randn(grid.shape, generator=g))
    m.decompose(tau=0.0)
    m.dynamic[:] = True
    return m


@pytest.mark.parametrize("coarse_to_fine", [True, False])
def test_batched_field_evaluation_matches_one_time_at_a_time(coarse_to_fine):
    m = moving_model(coarse_to_fine=coarse_to_fine)
    idx = torch.arange(len(m))
    times = [0.31, 0.37, 0.25]
    batched = m.offsets_at(idx, times)
    single = [m.offsets(idx, t) for t in times]
    assert len(batched) == 3
    for b, s in zip(batched, single):
        assert b.dx.abs().max() > 1e-3  # the field moves things
        assert torch.allclose(b.cat(), s.cat(), rtol=1e-5, atol=1e-7)
    # The same gradients reach the planes, the networks and the canonical means.
    params = [*m.deform.parameters(), *m.fine.parameters(), m.params.means]
    weights = torch.randn(3, len(m), 9, generator=torch.Generator().manual_seed(3))
    grads_b = torch.autograd.grad(sum((w * o.cat()).sum() for w, o in zip(weights, batched)), params, allow_unused=True)
    grads_s = torch.autograd.grad(sum((w * o.cat()).sum() for w, o in zip(weights, single)), params, allow_unused=True)
    assert grads_b[0] is not None and grads_b[-1] is not None  # the planes and the means
    for gb, gs in zip(grads_b, grads_s):
        assert (gb is None) == (gs is None)  # the fine residual is unused without C.F.
        assert gb is None or torch.allclose(gb, gs, rtol=1e-4, atol=1e-6)


# 16 and 32 channels run the kernels compiled for the presets' counts; 4 and 20 the general ones.
@pytest.mark.parametrize("spatial,temporal,features,multires", [(32, 16, 16, (1,)), (8, 5, 32, (1,)), (8, 5, 4, (1, 2)), (6, 3, 20, (1,))])
def test_fused_kplanes_kernel_matches_grid_sample(spatial, temporal, features, multires):
    """The C++ K-Planes kernel against the grid_sample expression (its oracle): features and
    the gradients of the coordinates and of every plane, points beyond the bound included
    (clamped onto the border), three times per point as the physical velocity asks."""
    from kgs_core.model.deformation import KPlanes
    from kgs_core.render import _ext

    if not _ext.compiler_available():
        pytest.skip("no C++ compiler")
    g = torch.Generator().manual_seed(features)
    planes = KPlanes(spatial, temporal, features, multires, bound=1.5)
    with torch.no_grad():
        for grid in planes.grids:
            grid.add_(0.3 * torch.randn(grid.shape, generator=g))
    n = 300
    x = (3.4 * torch.rand(n, 3, generator=g) - 1.7).requires_grad_(True)
    times = [torch.rand(n, generator=g) for _ in range(3)]
    weights = torch.randn(3 * n, planes.out_dim, generator=g)
    results = {}
    for backend in ("cpu", "torch"):
        feats = planes.at_times(x, times, backend=backend)
        results[backend] = (feats, torch.autograd.grad((feats * weights).sum(), [x, *planes.grids]))
    (f_cpu, g_cpu), (f_ref, g_ref) = results["cpu"], results["torch"]
    assert f_cpu.shape == (3 * n, planes.out_dim)
    assert torch.allclose(f_cpu, f_ref, atol=1e-6)
    assert g_ref[0].abs().max() > 1.0 and all(gr.abs().max() > 0.1 for gr in g_ref[1:])
    assert torch.allclose(g_cpu[0], g_ref[0], rtol=1e-5, atol=1e-4)
    for a, b in zip(g_cpu[1:], g_ref[1:]):
        assert torch.allclose(a, b, atol=1e-5)


def test_neighbour_mean_is_the_gathered_mean_forward_and_backward():
    m = moving_model(n=40)
    knn = m.knn_index().clone()
    knn[3, 1] = knn[3, 0]  # a repeated neighbour counts twice, as in the gather
    m._knn = knn
    x = torch.randn(40, 27, generator=torch.Generator().manual_seed(1), requires_grad=True)
    g = torch.randn(40, 27, generator=torch.Generator().manual_seed(2))
    sparse = m.neighbour_mean(x)
    gathered = x[knn].mean(1)
    assert torch.allclose(sparse, gathered, atol=1e-6)
    (grad_sparse,) = torch.autograd.grad((sparse * g).sum(), x)
    (grad_gathered,) = torch.autograd.grad((gathered * g).sum(), x)
    assert grad_gathered.abs().max() > 0.1
    assert torch.allclose(grad_sparse, grad_gathered, atol=1e-6)
    m._knn = knn[:, :1].contiguous()  # a new graph: the cached matrices are rebuilt
    assert torch.allclose(m.neighbour_mean(x), x[knn[:, 0]], atol=1e-7)


def test_coarse_neighbourhoods_do_not_reach_a_far_cluster():
    """C.F. averages a dynamic Gaussian's offsets over its nearest dynamic neighbours within
    `knn_radius` median 8th-neighbour distances: a Gaussian alone beside the moving cluster, far
    beyond that, keeps its own offsets instead of taking the cluster's motion; unbounded
    (`knn_radius` 0, and runs saved before the bound) it averages the cluster's."""
    g = torch.Generator().manual_seed(0)
    pts = torch.cat([0.05 * torch.randn(40, 3, generator=g), torch.tensor([[2.0, 0.0, 0.0]])])
    for radius, alone in ((3.0, True), (0.0, False)):
        m = KinematicsGS(
            init_from_points(pts.numpy(), np.full((41, 3), 0.5), 1, 4),
            ModelConfig(feature_dim=4, deform_spatial=8, deform_temporal=4, deform_features=4, deform_multires=(1, 2), knn_radius=radius),
        )
        m.decompose(tau=0.0)
        m.dynamic[:] = True
        knn = m.knn_index()
        assert (knn[-1] == 40).all().item() is alone, knn[-1]
        assert (knn[:40] < 40).all()  # the cluster's own neighbourhoods are untouched
    assert (
        ModelConfig.from_dict({k: v for k, v in ModelConfig().to_dict().items() if k not in ("knn_radius", "config_version")}).knn_radius
        == 0
    )  # saved before both


@pytest.mark.parametrize("coarse_to_fine", [True, False])
def test_physical_velocity_is_the_central_difference_of_the_coarse_deformed_position(coarse_to_fine):
    """The velocity K.R. uses: the central difference of the deformed position over the
    exposure, without the per-Gaussian fine residual's change (C.F. evaluates it at t only);
    the position itself keeps the fine residual."""
    m = moving_model(velocity="physical", coarse_to_fine=coarse_to_fine)
    idx = torch.arange(len(m))
    t, dt, exposure = 0.4, 0.05, 0.8
    g = m.at(t, exposure=exposure, dt=dt)
    h = 0.5 * dt * exposure

    def fine(at):
        if not coarse_to_fine:
            return 0.0
        return m.fine(m.params.features[idx], torch.full((len(m),), at)).dx

    full = (m.positions(idx, t + h)[0] - m.positions(idx, t - h)[0]) / (2 * h)
    expected = full - (fine(t + h) - fine(t - h)) / (2 * h)
    assert torch.allclose(g.velocity, expected.detach(), rtol=1e-4, atol=1e-5)
    if coarse_to_fine:  # the fine residual does move with time: leaving it out is a choice
        assert not torch.allclose(g.velocity, full.detach(), rtol=1e-3, atol=1e-4)
    assert torch.allclose(g.means, m.positions(idx, t)[0], rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("coarse_to_fine", [True, False])
def test_velocity_without_gradient_is_the_same_velocity_and_trains_the_field_only_through_positions(coarse_to_fine):
    """`velocity_grad=False`: the same velocities, positions and blurred covariances, but the
    sweep carries no gradient into the deformation field (its positions still do)."""
    t, dt, exposure = 0.4, 0.05, 0.8
    outs = {}
    for grad in (True, False):
        m = moving_model(velocity="physical", coarse_to_fine=coarse_to_fine, velocity_grad=grad)
        g = m.at(t, exposure=exposure, dt=dt)
        idx, sweep = g.sweep
        field = list(m.deform.parameters())
        from_sweep = torch.autograd.grad(sweep.square().sum(), field, allow_unused=True, retain_graph=True) if sweep.requires_grad else []
        from_means = torch.autograd.grad(g.means.square().sum(), field, allow_unused=True)
        outs[grad] = (g, from_sweep, from_means)
    (a, sweep_grads, _), (b, no_sweep_grads, means_grads) = outs[True], outs[False]
    assert torch.allclose(a.velocity, b.velocity, rtol=1e-5, atol=1e-6)
    assert torch.allclose(a.means, b.means) and torch.allclose(a.covars6, b.covars6, rtol=1e-5, atol=1e-7)
    assert any(x is not None and x.abs().sum() > 0 for x in sweep_grads)
    assert not no_sweep_grads  # the sweep does not depend on the field's parameters
    assert any(x is not None and x.abs().sum() > 0 for x in means_grads)


@pytest.mark.parametrize("kr_form", ["convolve", "paper"])
def test_sharp_render_skips_the_velocity_only_where_nothing_depends_on_it(kr_form, monkeypatch):
    """`at` / `at_dynamic(..., velocity=False)`: at exposure 0 under the convolve form the Gaussians are the
    same without the velocity, so its two extra field samples are skipped; under the paper's
    form (whose basis follows v even when sharp) and at exposure > 0 they are not."""
    m = moving_model(velocity="physical", kr_form=kr_form)
    times_seen = []
    at_times = m.deform.at_times
    monkeypatch.setattr(m.deform, "at_times", lambda x, tt, **kw: times_seen.append(len(tt)) or at_times(x, tt, **kw))
    for exposure in (0.0, 0.7):
        full = m.at(0.4, exposure=exposure, dt=0.05)
        lean = m.at(0.4, exposure=exposure, dt=0.05, velocity=False)
        skipped = exposure == 0 and kr_form == "convolve"
        assert times_seen[-2:] == [3, 1 if skipped else 3]
        assert (lean.velocity is None) == skipped
        assert full.velocity.abs().max() > 1e-3
        assert torch.allclose(lean.means, full.means, rtol=1e-5, atol=1e-7)
        assert torch.allclose(lean.covars6, full.covars6, rtol=1e-4, atol=1e-9)
        if exposure > 0 and kr_form == "convolve":  # the velocity does shape the blurred covariance
            assert not torch.allclose(m.at(0.4, exposure=0.0, dt=0.05).covars6, full.covars6, rtol=1e-4, atol=1e-9)
            # ... and the sweep handed to the renderer (for the splats' mass) is the one it used
            idx, sweep = full.sweep
            assert torch.equal(idx, torch.arange(len(m)))
            assert torch.allclose(sweep.detach(), full.velocity * 0.05 * exposure, rtol=1e-6, atol=1e-9)
        else:
            assert full.sweep is None and lean.sweep is None
        # The server's dynamic-only path makes the same choice.
        _, lean_dyn = m.at_dynamic(0.4, exposure, 0.05, velocity=False)
        assert times_seen[-1] == (1 if skipped else 3) and (lean_dyn.velocity is None) == skipped
        assert torch.allclose(lean_dyn.covars6, full.covars6, rtol=1e-4, atol=1e-9)


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_residual_covariance_equals_the_rotation_matrix_form_with_its_gradients(backend, monkeypatch):
    """The deformed covariance composes `R(q) exp(dr)` as quaternions and packs it in one op;
    it must equal the matrix form `M Mᵀ`, `M = R(q) so3_exp(dr) diag(s exp(λ ds))`, in value
    and gradient, for rotations from zero (the series branches) to beyond pi, and for
    unnormalised quaternions."""
    import kgs_core.model.kinematics as kin
    from kgs_core.model.kinematics import so3_exp
    from kgs_core.render.covariance import quat_to_rotmat

    monkeypatch.setattr(kin, "packed_covariance", lambda q, s: packed_covariance(q, s, backend=backend))
    g = torch.Generator().manual_seed(3)
    n = 40
    quats = (torch.randn(n, 4, generator=g) * 2).requires_grad_(True)
    scales = (torch.rand(n, 3, generator=g) * 0.2 + 0.01).requires_grad_(True)
    angles = torch.cat(
        [
            torch.zeros(4),
            torch.full((4,), 1e-7),
            torch.full((4,), 1e-4),
            torch.rand(n - 16, generator=g) * 3.0,
            torch.tensor([3.3, 3.6, 4.0, 6.0]),
        ]
    )
    axes = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    dr = (axes * angles[:, None]).requires_grad_(True)
    ds = (torch.randn(n, 3, generator=g) * 0.5).requires_grad_(True)
    weights = torch.randn(n, 6, generator=g)

    def grads(cov6):
        for t in (quats, scales, dr, ds):
            t.grad = None
        (cov6 * weights).sum().backward()
        return cov6.detach(), [t.grad.clone() for t in (quats, scales, dr, ds)]

    got, got_grads = grads(kin.residual_covariance(quats, scales, Offsets(torch.zeros(n, 3), dr, ds), 0.1))
    M = quat_to_rotmat(quats) @ so3_exp(dr) * (scales * torch.exp(0.1 * ds))[:, None, :]
    want, want_grads = grads(pack_covariance(M @ M.transpose(-1, -2)))
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-8)
    for a, b in zip(got_grads, want_grads):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-5)


def test_packed_covariances_through_the_model_match_the_full_matrices():
    """Static Gaussians: the packed C++ covariance equals `R S S^T R^T` in PyTorch; a render
    from packed `(N, 6)` covariances equals one from `(N, 3, 3)`, gradients included."""
    m = moving_model(n=64)
    m.decompose(tau=1e9)  # all static
    g = m.at(0.5)
    ref = covariance_from_quat_scale(m.params.quats, m.scales())
    assert torch.allclose(g.covars, ref, rtol=1e-5, atol=1e-9)
    assert torch.allclose(unpack_covariance(pack_covariance(ref)), ref, rtol=1e-6, atol=1e-12)
    assert torch.allclose(packed_covariance(m.params.quats, m.scales(), backend="torch"), g.covars6, rtol=1e-5, atol=1e-9)

    viewmat = look_at([0.0, 0.0, -2.5], [0.0, 0.0, 0.0])
    K = intrinsics(40, 32, 45.0)
    cov6 = g.covars6.detach().requires_grad_(True)
    cov33 = unpack_covariance(cov6.detach()).requires_grad_(True)
    colors = torch.rand(len(m), 3, generator=torch.Generator().manual_seed(0))
    packed = rasterize(g.means.detach(), g.opacities.detach(), viewmat, K, 40, 32, covars=cov6, colors=colors)
    full = rasterize(g.means.detach(), g.opacities.detach(), viewmat, K, 40, 32, covars=cov33, colors=colors)
    assert packed.alpha.max() > 0.1
    assert torch.allclose(packed.image, full.image, atol=1e-6)
    packed.image.sum().backward()
    full.image.sum().backward()
    # d/d(cov6) of the off-diagonal entries is the sum of the two symmetric matrix entries.
    assert torch.allclose(cov6.grad, pack_covariance(cov33.grad) * torch.tensor([1, 2, 2, 1, 2, 1]), rtol=1e-4, atol=1e-6)
    with pytest.raises(ValueError, match=r"\(N, 3, 3\) or packed \(N, 6\)"):
        rasterize(g.means, g.opacities, viewmat, K, 40, 32, covars=cov6[:, :5], colors=colors)


def test_blurred_splat_keeps_the_mass_of_the_sharp_one_swept_over_the_exposure():
    """A Gaussian blurred by the convolve form (`Σ + s sᵀ/12`, opacity scaled by
    `blur_opacity_scale`) covers the image like the sharp Gaussian averaged over its path,
    in total (its mass) and in shape; with the opacity left alone it would cover ~1.9x more."""
    from kgs_core.render.blur import blur_opacity_scale

    viewmat = look_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0])
    W = H = 64
    K = intrinsics(W, H, 50.0)
    mean = torch.tensor([[0.05, -0.02, 0.1]])
    sigma = covariance_from_quat_scale(torch.tensor([[0.9, 0.1, 0.3, 0.2]]), torch.tensor([[0.05, 0.03, 0.01]]))
    sweep = torch.tensor([[0.25, 0.1, 0.05]])  # ~6 px on screen, the splat ~1 px wide
    opacity = torch.tensor([0.3])
    white = torch.ones(1, 1)
    blurred = pack_covariance(sigma + sweep[:, :, None] * sweep[:, None, :] / 12)
    scale = blur_opacity_scale(mean, blurred, sweep, viewmat, K, W, H)
    one = lambda m, cov, o: rasterize(m, o, viewmat, K, W, H, covars=cov, colors=white).alpha[..., 0]  # noqa: E731
    offsets = (torch.arange(256) + 0.5) / 256 - 0.5
    swept = torch.stack([one(mean + o * sweep, pack_covariance(sigma), opacity) for o in offsets]).mean(0)
    compensated = one(mean, blurred, opacity * scale)
    plain = one(mean, blurred, opacity)
    assert 0.45 < float(scale) < 0.6
    assert float(compensated.sum()) == pytest.approx(float(swept.sum()), rel=0.02)
    assert float(plain.sum()) > 1.7 * float(swept.sum())
    # the blurred splat is the swept one's second-moment match: the shapes differ by a seventh
    # of the mass (a Gaussian against a box-filtered one), the plain one by almost all of it
    assert float((compensated - swept).abs().sum()) < 0.16 * float(swept.sum())
    assert float((plain - swept).abs().sum()) > 0.8 * float(swept.sum())

    # The factor is sqrt(det Σ2_sharp / det Σ2_blur) of the rasteriser's own 2D covariances.
    from kgs_core.render.torch_backend import project

    def det2d(cov6):
        c = project(mean, cov6, opacity, viewmat, K, W, H, 0.01, 1e10, 0.3, False).conics[0]
        return 1.0 / float(c[0] * c[2] - c[1] * c[1])

    assert float(scale) == pytest.approx((det2d(pack_covariance(sigma)) / det2d(blurred)) ** 0.5, rel=1e-4)


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_blur_opacity_scale_matches_the_determinant_ratio_with_its_gradients(backend):
    """Both backends against autograd through the determinant ratio itself (float64),
    Gaussians off screen and behind the camera included."""
    from kgs_core.render.blur import blur_opacity_scale
    from kgs_core.render.torch_backend import camera_jacobian

    g = torch.Generator().manual_seed(3)
    B = 60
    viewmat = look_at([0.3, -0.2, -3.0], [0.0, 0.0, 0.0]).double()
    K = intrinsics(64, 48, 50.0).double()
    means = 1.5 * torch.randn(B, 3, generator=g, dtype=torch.float64)
    means[0] = torch.tensor([0.0, 0.0, -3.5], dtype=torch.float64)  # behind the camera
    A = 0.05 * torch.randn(B, 3, 3, generator=g, dtype=torch.float64)
    sweep = (0.1 * torch.randn(B, 3, generator=g, dtype=torch.float64)).requires_grad_(True)
    sigma = A @ A.transpose(1, 2) + 1e-4 * torch.eye(3, dtype=torch.float64)
    cov6 = pack_covariance(sigma + sweep.detach()[:, :, None] * sweep.detach()[:, None, :] / 12).requires_grad_(True)
    scale = blur_opacity_scale(means, cov6, sweep, viewmat, K, 64, 48, backend=backend)
    w = torch.rand(B, generator=g, dtype=torch.float64)
    gc, gs = torch.autograd.grad((scale * w).sum(), [cov6, sweep])

    _, _, J = camera_jacobian(means, viewmat, K, 64, 48, 0.01, 1e10)
    M = J @ viewmat[:3, :3]
    cov6r, sweepr = cov6.detach().clone().requires_grad_(True), sweep.detach().clone().requires_grad_(True)
    blur2 = M @ unpack_covariance(cov6r) @ M.transpose(1, 2) + 0.3 * torch.eye(2, dtype=torch.float64)
    s2 = M @ sweepr[:, :, None]
    ref = (torch.linalg.det(blur2 - s2 @ s2.transpose(1, 2) / 12) / torch.linalg.det(blur2)).sqrt()
    rc, rs = torch.autograd.grad((ref * w).sum(), [cov6r, sweepr])
    assert scale.min() < 0.9 and scale.max() <= 1
    assert torch.allclose(scale, ref, rtol=1e-10)
    assert torch.allclose(gc, rc, rtol=1e-7, atol=1e-9)
    assert torch.allclose(gs, rs, rtol=1e-7, atol=1e-9)
    # float32 through the C++ kernel agrees with the reference too
    if backend == "cpu":
        f32 = blur_opacity_scale(means.float(), cov6.detach().float(), sweep.detach().float(), viewmat.float(), K.float(), 64, 48)
        assert torch.allclose(f32.double(), ref.detach(), rtol=1e-4, atol=1e-5)


def test_otsu_tau_cuts_between_the_still_mode_and_the_moving_tail():
    """τ picked from the distribution of K: between a still mode and a moving one (on log10 K),
    never below the floor, and the floor itself when there is one mode only."""
    from kgs_core.model.decomposition import otsu_tau

    g = torch.Generator().manual_seed(0)
    still = 10 ** (-4.5 + 0.2 * torch.randn(8000, generator=g))  # real footage: jitter well above a fixed τ
    moving = 10 ** (-2.0 + 0.3 * torch.randn(2000, generator=g))
    tau = otsu_tau(torch.cat([still, moving]), floor=2e-6)
    assert 10**-4.0 < tau < 10**-2.8
    assert abs(float((torch.cat([still, moving]) > tau).float().mean()) - 0.2) < 0.01
    assert otsu_tau(torch.cat([still, moving]), floor=0.05) == 0.05  # the floor wins
    assert otsu_tau(torch.full((100,), 3e-5), floor=2e-6) == 2e-6  # nothing to separate
    assert otsu_tau(torch.zeros(0), floor=1e-5) == 1e-5


def test_otsu_tau_leaves_out_the_gaussians_the_field_leaves_still():
    """A third mode of Gaussians the field barely moves (far below the floor, as on real
    footage) took Otsu's cut for itself, and the floor then called nearly every Gaussian
    dynamic; `from_share` keeps them out of the split and the cut is again between the
    residual-motion mode and the moving tail."""
    from kgs_core.model.decomposition import otsu_tau

    g = torch.Generator().manual_seed(1)
    still = 10 ** (-10.0 + 1.5 * torch.randn(2000, generator=g))  # untouched by the field
    jitter = 10 ** (-5.3 + 0.4 * torch.randn(7000, generator=g))  # residual pose error, above the floor
    moving = 10 ** (-2.0 + 0.3 * torch.randn(1000, generator=g))
    K, floor = torch.cat([still, jitter, moving]), 2.6e-6
    assert otsu_tau(K, floor) == floor  # every Gaussian read: the cut falls under the floor
    assert float((K > floor).float().mean()) > 0.6
    tau = otsu_tau(K, floor, from_share=0.01)
    assert 10**-4.5 < tau < 10**-2.8
    assert abs(float((K > tau).float().mean()) - 0.1) < 0.01
    assert otsu_tau(jitter, floor, from_share=0.01) == otsu_tau(jitter, floor)  # nothing left out
    assert otsu_tau(still, floor, from_share=0.01) == floor  # none the field moves: the floor


def test_static_field_offsets_are_the_fields_own_under_a_sample_of_static_gaussians():
    """L_reg's static term: the field's offsets under static Gaussians (which render without
    it), at most `count` of them, with gradients into the field only."""
    m = moving_model(n=40)
    m.dynamic[:] = False
    m.dynamic[:10] = True
    t = 0.3
    all_static = m.static_field_dx(t, count=1000)
    assert all_static.shape == (30, 3)
    expected = m.deform(m.params.means.detach()[10:], torch.full((30,), t)).dx
    torch.testing.assert_close(all_static, expected)
    assert all_static.abs().max() > 1e-3  # this field moves things: the term is not vacuous
    sample = m.static_field_dx(t, count=8)
    assert sample.shape == (8, 3)
    sample.norm(dim=-1).mean().backward()
    assert m.params.means.grad is None  # positions are not pulled by the term
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in m.deform.parameters())


def test_temporal_variance_is_the_papers_k_of_the_fields_offsets():
    """K_i = mean over T evenly spaced times of |dx_i(t) - mean_t dx_i(t)|^2, from the
    deformation field alone (no coarse-to-fine averaging, no time noise), written out here
    with a field whose offsets are known."""
    m = moving_model(n=40, K_times=5)
    x = m.params.means.detach()
    # A known field: dx = (t^2 a_i, sin(3 t) b_i, c_i), with per-point a, b, c.
    g = torch.Generator().manual_seed(3)
    a, b, c = (torch.randn(len(x), generator=g) for _ in range(3))
    rows = {tuple(p.tolist()): i for i, p in enumerate(x)}

    def field(points, times):
        i = torch.tensor([rows[tuple(p.tolist())] for p in points])
        out = []
        for t in times:
            dx = torch.stack([t**2 * a[i], torch.sin(3 * t) * b[i], c[i]], -1)
            z = torch.zeros_like(dx)
            out.append(Offsets(dx, z, z))
        return out

    m.deform.at_times = field
    k = m.compute_K(chunk=16)  # chunks smaller than N: the rows must line up
    ts = torch.linspace(0, 1, 5)
    dx = torch.stack([torch.stack([t**2 * a, torch.sin(3 * t) * b, c], -1) for t in ts])  # (T, N, 3)
    expected = ((dx - dx.mean(0)) ** 2).sum(-1).mean(0)
    torch.testing.assert_close(k, expected)
    assert float(k.min()) > 0  # every point moves; the constant z offset adds nothing
    # The decomposition: dynamic exactly where K exceeds tau.
    tau = float(expected.median())
    assert torch.equal(m.decompose(tau, recompute=True), expected > tau)


def test_split_in_place_keeps_each_gaussian_where_it_renders_on_average():
    """A decomposition in place moves a Gaussian that turns static to its time-averaged deformed mean,
    rotation and scale (exactly: a static Gaussian has no field), leaves untouched those that
    stay static, and keeps the average position of the rest closer than a plain decomposition does;
    with keep_static no static Gaussian turns dynamic."""
    from kgs_core.model.kinematics import residual_covariance

    def average_state(m):
        off = m.mean_offsets()
        return m.params.means.detach() + off[:, :3], off

    plain, moved = moving_model(n=64), moving_model(n=64)
    x0, off0 = average_state(moved)
    assert float(off0[:, :3].norm(dim=-1).median()) > 0.05  # the field's mean offsets are not small
    k = moved.compute_K()
    tau = float(k.median())
    for m, in_place in ((plain, False), (moved, True)):
        m.K = k.clone()
        m.decompose(tau, recompute=False, in_place=in_place)
    turned = ~moved.dynamic
    assert torch.equal(turned, ~plain.dynamic) and 20 < int(turned.sum()) < 44
    x1, _ = average_state(moved)
    torch.testing.assert_close(x1[turned], x0[turned], atol=1e-6, rtol=0)
    jumped = (average_state(plain)[0] - x0).norm(dim=-1)
    assert float(jumped[turned].min()) > 1e-3  # ... where a plain decomposition makes them jump
    # Their covariance is the deformed one at the mean offsets.
    with torch.no_grad():
        was = unpack_covariance(
            residual_covariance(plain.params.quats[turned], plain.scales()[turned], Offsets.from_cat(off0[turned]), moved.config.lambda_s)
        )
        now = covariance_from_quat_scale(moved.params.quats[turned], moved.scales()[turned])
    torch.testing.assert_close(now, was, atol=1e-6, rtol=1e-4)
    # The ones that stay dynamic: on average nearer where they were than after a plain decomposition.
    stay = moved.dynamic
    # (Their kNN neighbours changed: a plain decomposition moved them by 0.01 on average here, in place
    # by 0.0007, not 0, since moving a canonical mean also moves the field's value there.)
    assert float(jumped[stay].mean()) > 1e-3
    assert float((x1 - x0)[stay].norm(dim=-1).mean()) < 0.2 * float(jumped[stay].mean())
    # A second decomposition: Gaussians static on both sides stay bit for bit.
    before = {k: v.detach().clone() for k, v in moved.params.items()}
    moved.decompose(2 * tau, recompute=False, in_place=True)
    still = turned & ~moved.dynamic
    assert int(still.sum()) > 0
    for name, value in moved.params.items():
        assert torch.equal(value.detach()[still], before[name][still]), name
    # keep_static (training's re-decompositions): a lower τ turns none of the static ones dynamic.
    static = ~moved.dynamic
    assert torch.equal(~moved.decompose(0.0, recompute=False, keep_static=True), static)
    assert moved.decompose(0.0, recompute=False).all()


def test_paper_form_of_kr_matches_eqs_9_to_14_worked_by_hand():
    """`refine_covariance` (`--kr-form paper`) on cases worked out by hand from the paper's
    eqs. 9-14: velocity along z, so the basis is u_x = e_y, u_y = -e_x, u_z = e_z (appendix A.1
    with the reference e_x); a diagonal covariance; then each term on its own."""
    from kgs_core.model.kinematics import kinematic_basis, refine_covariance

    f64 = torch.float64
    v = torch.tensor([[0.0, 0.0, 2.0]], dtype=f64)
    assert torch.allclose(kinematic_basis(v), torch.tensor([[[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]], dtype=f64))
    sigma = torch.diag(torch.tensor([0.1, 0.2, 0.3], dtype=f64) ** 2)[None]
    zero = torch.zeros(1, 3, dtype=f64)
    far = torch.tensor([1e3], dtype=f64)  # per-frame motion far above still_len: no blend toward sigma

    def refine(blur, ds=zero, dr=zero, r_z=(0.0, 0.0, 1.0), kappa=-2.0, frame_len=far):
        return refine_covariance(
            sigma, v, torch.tensor([blur], dtype=f64), ds, dr, torch.tensor([r_z], dtype=f64), torch.tensor(kappa, dtype=f64), frame_len
        )[0]

    # Eq. 9-10: s' = (sigma along u_x, along u_y, along u_z + eta |v| dt e) = (0.2, 0.1, 0.3 + 0.4),
    # with eta = |r_z . u_z| = 1 (eq. 11); rebuilt in the world frame, x takes u_y's scale.
    assert torch.allclose(refine(0.4), torch.diag(torch.tensor([0.1, 0.2, 0.7], dtype=f64) ** 2), atol=1e-9)
    # Eq. 11's lower bound: r_z across the motion gives eta = sigmoid(kappa) = 0.5.
    assert torch.allclose(refine(0.4, r_z=(1.0, 0.0, 0.0), kappa=0.0), torch.diag(torch.tensor([0.1, 0.2, 0.5], dtype=f64) ** 2), atol=1e-9)
    # Eq. 12-13: log s = log s' + lambda_s ds, lambda_s = 0.1.
    ds = torch.tensor([[0.5, -0.5, 1.0]], dtype=f64)
    s = torch.tensor([0.2, 0.1, 0.7], dtype=f64) * torch.exp(0.1 * ds[0])  # along (u_x, u_y, u_z)
    assert torch.allclose(refine(0.4, ds=ds), torch.diag(torch.stack([s[1], s[0], s[2]]) ** 2), atol=1e-9)
    # Eq. 14: R = R_kin exp(dr); a quarter turn about u_z swaps which world axis gets which scale.
    dr = torch.tensor([[0.0, 0.0, math.pi / 2]], dtype=f64)
    assert torch.allclose(refine(0.4, dr=dr), torch.diag(torch.tensor([0.2, 0.1, 0.7], dtype=f64) ** 2), atol=1e-9)
    # A Gaussian moving by still_len per frame is halfway blended toward its predicted covariance.
    half = refine(0.4, frame_len=torch.tensor([1e-3], dtype=f64))
    assert torch.allclose(half, 0.5 * (sigma[0] + refine(0.4)), atol=1e-12)


def test_pruning_and_adding_resize_every_per_gaussian_tensor_in_lock_step():
    """`keep_gaussians` / `add_gaussians` carry the parameters, their Adam moments, the dynamic
    flags, K, own velocities and a strategy's statistics together; each survivor keeps its own
    values, each new Gaussian its parent's flag, K and own velocity with zero moments and
    statistics."""
    from kgs_core.model.gaussians import GaussianParams
    from kgs_core.train.densify import DensifyStrategy

    m = moving_model(n=10)
    m.dynamic[:5] = False
    m.K = torch.arange(10.0)
    m.own_velocity = torch.arange(10.0)[:, None].repeat(1, 3)
    opt = torch.optim.Adam([{"params": [v], "name": k} for k, v in m.params.items()], lr=1e-3)
    sum(v.sum() for _, v in m.params.items()).backward()
    opt.step()
    strategy = DensifyStrategy()
    strategy.reset(10)
    strategy.state["grad_sum"] += torch.arange(10.0) * 2
    keep = torch.tensor([i % 3 != 0 for i in range(10)])  # 1 2 4 5 7 8
    means, moment = m.params.means.detach()[keep].clone(), opt.state[m.params.means]["exp_avg"][keep].clone()
    m.keep_gaussians(keep, opt, strategy.state)
    assert len(m) == 6 and torch.equal(m.K, torch.tensor([1.0, 2, 4, 5, 7, 8]))
    assert torch.equal(m.own_velocity[:, 0], m.K)
    assert torch.equal(m.dynamic, torch.tensor([False, False, False, True, True, True]))
    assert torch.equal(strategy.state["grad_sum"], 2 * m.K) and len(strategy.state["count"]) == 6
    assert torch.equal(m.params.means.detach(), means) and torch.equal(opt.state[m.params.means]["exp_avg"], moment)
    parents = torch.tensor([0, 5])
    new = GaussianParams(*(v.detach()[parents].clone() for _, v in m.params.items()))
    m.add_gaussians(new, parents, opt, strategy.state)
    assert len(m) == 8 and torch.equal(m.K[6:], torch.tensor([1.0, 8.0]))
    assert torch.equal(m.own_velocity[:, 0], m.K)
    assert torch.equal(m.dynamic[6:], torch.tensor([False, True]))
    assert torch.equal(strategy.state["grad_sum"][6:], torch.zeros(2)) and len(strategy.state["count"]) == 8
    assert torch.equal(opt.state[m.params.means]["exp_avg"][6:], torch.zeros(2, 3))
    # A strategy left behind by a resize that did not carry it is an error, not silently zeroed.
    m.keep_gaussians(torch.ones(8, dtype=torch.bool).index_fill_(0, torch.tensor([0]), False), opt)
    with pytest.raises(RuntimeError, match="statistics cover 8 Gaussians, the model has 7"):
        strategy._ensure(len(m))


def test_densification_carries_the_coarse_to_fine_graph_instead_of_rebuilding_it():
    """Adding and pruning Gaussians keeps every dynamic Gaussian's kNN neighbours, though the
    canonical means have moved since the graph was built: a clone (here at its parent's very
    spot) changes no other Gaussian's offsets, and a densification split's child takes its parent's row with
    itself in its parent's place. A rebuilt graph would give Gaussians other neighbours, and so
    other coarse offsets under fine residuals fitted to the old ones."""
    from kgs_core.model.gaussians import GaussianParams

    m = moving_model(n=40)
    m.dynamic[:4] = False  # the graph indexes the dynamic subset
    m._knn = None
    graph = m.knn_index().clone()
    with torch.no_grad():  # training moves the canonical means after the graph is built
        m.params.means.add_(0.1 * torch.randn(40, 3, generator=torch.Generator().manual_seed(3)))
    dyn = torch.nonzero(m.dynamic).squeeze(1)
    before = m.offsets(dyn, 0.3).cat().detach()
    parents = torch.tensor([2, 10, 17])  # a static one and two dynamic ones (rows 6 and 13)
    m.add_gaussians(GaussianParams(*(v.detach()[parents].clone() for _, v in m.params.items())), parents)
    knn = m.knn_index()
    assert torch.equal(knn[:36], graph) and len(knn) == 38
    for row, parent_row in ((36, 6), (37, 13)):
        assert torch.equal(knn[row], torch.where(graph[parent_row] == parent_row, row, graph[parent_row]))
    after = m.offsets(torch.nonzero(m.dynamic).squeeze(1), 0.3).cat().detach()
    assert torch.allclose(after[:36], before, atol=1e-6)
    assert torch.allclose(after[36:], before[[6, 13]], atol=1e-6)  # each clone moves as its parent
    # Gaussian 10 (row 6) leaves with the clone appended for it (Gaussian 41, row 36) as its heir;
    # Gaussian 20 (row 16) leaves with none: its neighbours average themselves in its place.
    keep = torch.ones(43, dtype=torch.bool)
    keep[[10, 20]] = False
    heirs = torch.full((43,), -1, dtype=torch.long)
    heirs[10] = 41
    m.keep_gaussians(keep, heirs=heirs)
    old_row = torch.tensor([r for r in range(38) if r not in (6, 16)])  # old row of each new row
    new_of_old = torch.full((38,), -1, dtype=torch.long)
    new_of_old[old_row] = torch.arange(36)
    new_of_old[6] = new_of_old[36]
    expected = new_of_old[torch.cat([graph, knn[36:]])[old_row]]
    expected = torch.where(expected >= 0, expected, torch.arange(36)[:, None])
    assert torch.equal(m.knn_index(), expected)


def test_a_re_split_carries_the_graph_of_the_gaussians_that_stay_dynamic():
    """At a re-decomposition the Gaussians that stay dynamic keep their neighbours (one turned static is
    replaced by the row's own Gaussian), and only those that turn dynamic get their nearest
    dynamic neighbours by canonical mean."""
    m = moving_model(n=30, knn_radius=0.0)
    m.dynamic[:6] = False
    m._knn = None
    graph = m.knn_index().clone()  # rows for Gaussians 6..29
    with torch.no_grad():  # training moves the canonical means after the graph is built
        m.params.means.add_(0.2 * torch.randn(30, 3, generator=torch.Generator().manual_seed(4)))
    dynamic = m.dynamic.clone()
    dynamic[[1, 3]] = True  # turn dynamic
    dynamic[[10, 20]] = False  # turn static
    m.K = dynamic.float()
    m.decompose(tau=0.5, recompute=False)
    members = torch.nonzero(dynamic).squeeze(1)
    new_row = torch.full((30,), -1, dtype=torch.long)
    new_row[members] = torch.arange(len(members))
    knn = m.knn_index()
    for r, g in enumerate(members.tolist()):
        if g in (1, 3):
            pts = m.params.means.detach()[members]
            nearest = (pts - pts[r]).norm(dim=-1).argsort()[:8]
            assert set(knn[r].tolist()) == set(nearest.tolist())
        else:
            old = new_row[6 + graph[g - 6]]  # old row j was Gaussian 6 + j
            assert torch.equal(knn[r], torch.where(old >= 0, old, r))


def test_a_split_childs_sibling_rows_point_at_the_first_child():
    """Adaptive density control passes the densification split parents' heirs on: the Gaussians that
    averaged a densification split parent average its first child, and no row points at a removed one."""
    from kgs_core.train.densify import DensifyStrategy

    m = moving_model(n=30)
    graph = m.knn_index().clone()
    with torch.no_grad():
        m.params.log_scales[5] = math.log(0.2)  # large: split, not cloned
    strategy = DensifyStrategy(grad_threshold=1e-4, max_gaussians=10_000, prune_opacity=0.0, extent=10.0)
    strategy.reset(30)
    strategy.state["grad_sum"][5], strategy.state["count"][5] = 1.0, 1.0
    strategy._densify_and_prune(m, None)
    assert len(m) == 31 and int(m.dynamic.sum()) == 31  # 30 - the parent + two children
    knn = m.knn_index()
    first_child = 29  # rows 0-4 and 6-29 close up to 0-28; the children follow, first one first
    pointed = (graph == 5).any(1)
    pointed[5] = False
    rows = torch.arange(30)[~(torch.arange(30) == 5)]
    assert torch.equal((knn[:29] == first_child).any(1), pointed[rows])
    assert int(knn.max()) < 31


def test_kr_effect_measures_the_blur_and_says_when_it_does_nothing(tmp_path):
    """`evaluate.kr_effect`: Gaussians the field moves, blurred over a whole frame interval,
    change many pixels visibly, and against frames that show that blur the blurred render fits
    them better (K.R. acts: no note). Over an exposure a thousand times shorter nothing changes
    visibly, and the note says that K.R. does next to nothing."""
    from kgs_core.data.images import write_image
    from kgs_core.data.scene import Camera, Frame
    from kgs_core.evaluate import KR_MIN_GAIN_DB, kr_effect, kr_effect_note, render_at

    m = moving_model(n=300, velocity="physical")
    with torch.no_grad():  # small opaque dots that the field moves by a few pixels per frame interval
        m.deform.mlp[-1].weight.mul_(2.0)
        m.params.log_scales.fill_(math.log(0.02))
        m.params.opacity_logits.fill_(3.0)
    cam = Camera(
        K=np.array([[200.0, 0, 48], [0, 200, 48], [0, 0, 1]]),
        viewmat=look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0), dtype=torch.float64).numpy(),
        width=96,
        height=96,
    )
    frames = []
    for i in range(3):
        write_image(tmp_path / f"{i}.png", np.full((96, 96, 3), 0.5, np.float32))
        frames.append(Frame(id=str(i), image_path=tmp_path / f"{i}.png", time=0.3 + 0.2 * i, camera=cam))
    long = kr_effect(m, frames, exposure=1.0, dt=0.2)
    short = kr_effect(m, frames, exposure=1e-3, dt=0.2)
    assert long["frames"] == short["frames"] == 3
    assert long["changed_share"] > 0.01, long  # visibly blurred
    # Frames that show that blur (the blurred renders themselves): modelling it is what fits them.
    for f in frames:
        write_image(f.image_path, render_at(m, f, 1.0, 0.2)[0].image.detach().clamp(0, 1).numpy())
    fits = kr_effect(m, frames, exposure=1.0, dt=0.2)
    assert fits["gain_db"] > KR_MIN_GAIN_DB and kr_effect_note(fits) is None, fits
    assert short["changed_share"] < 1e-3 and abs(short["gain_db"]) < 0.01, short
    assert "does next to nothing" in kr_effect_note(short) and "which --camera-blur models" in kr_effect_note(short)
    # With the camera's blur modelled (--camera-blur), the blurred render has it too: a camera
    # sliding sideways by ~25 px over the exposure smears far more than the Gaussians' own motion.
    slide = (torch.zeros(3, 3), torch.tensor([2.0, 0.0, 0.0]))
    with_camera = kr_effect(m, frames, exposure=1.0, dt=0.2, camera_motion=lambda f: slide)
    assert with_camera["camera_blur"] and not long["camera_blur"]
    assert with_camera["changed_share"] > long["changed_share"] + 0.05, (with_camera, long)
    still = kr_effect(m, frames, exposure=1e-3, dt=0.2, camera_motion=lambda f: slide)
    assert "of the camera" in kr_effect_note(still), kr_effect_note(still)


def test_the_opacity_reset_caps_each_gaussian_as_rendered_at_its_most_opaque_time():
    """A dynamic Gaussian that the time opacity fades at every time is capped so that it
    renders at 0.01 at its most opaque time, above the rasteriser's 1/255: with its logit
    capped at logit(0.01) it would render under 1/255 at every time, get no gradient and never
    come back. Gaussians without a time opacity (a spawned one, a model without it) are
    capped at 0.01 as before, and one already below the cap is left alone."""
    from kgs_core.render.types import ALPHA_MIN
    from kgs_core.train.densify import DensifyStrategy

    times = torch.linspace(0, 1, 33).tolist()
    m = moving_model(seed=3, time_opacity=True)
    m.lifespan[5] = torch.tensor([0.5, 0.1])  # a spawned Gaussian: its lifespan, not the net
    with torch.no_grad():
        m.params.features.normal_(generator=torch.Generator().manual_seed(0))
        m.time_opacity.mlp[-1].weight.normal_(0, 0.2, generator=torch.Generator().manual_seed(1))
        m.time_opacity.mlp[-1].bias.fill_(-2.0)  # faded to about a fifth at every time
        m.params.opacity_logits.fill_(3.0)
        m.params.opacity_logits[7] = math.log(0.002 / 0.998)  # already below the cap
    offsets = m.peak_opacity_offsets()
    assert offsets[5] == 0 and (offsets[torch.arange(len(m)) != 5] < -1.0).all(), offsets
    old_peak = torch.sigmoid(math.log(0.01 / 0.99) + offsets)  # the logit capped alone
    assert (old_peak[torch.arange(len(m)) != 5] < ALPHA_MIN).all()
    kept = m.params.opacity_logits[7].item()
    DensifyStrategy(opacity_reset_at=(10,)).reset_opacities(m, None, 10)
    with torch.no_grad():
        peak = torch.stack([m.at(t, velocity=False).opacities for t in times]).max(0).values
    others = torch.tensor([i not in (5, 7) for i in range(len(m))])
    assert torch.allclose(peak[others], torch.full_like(peak[others], 0.01), rtol=1e-3), peak
    assert peak[5] == pytest.approx(0.01, rel=1e-4)  # the spawned one, at its own time
    assert m.params.opacity_logits[7].item() == kept
    plain = moving_model(seed=3)
    with torch.no_grad():
        plain.params.opacity_logits.fill_(3.0)
    DensifyStrategy(opacity_reset_at=(10,)).reset_opacities(plain, None, 10)
    assert torch.allclose(plain.params.opacities, torch.full((len(plain),), 0.01))


def test_pruning_reads_each_gaussians_opacity_at_its_most_opaque_time():
    """A dynamic Gaussian that the time opacity fades under the prune threshold at every time
    is pruned though its own opacity is high: it adds nothing to any frame and, under 1/255,
    gets no gradient to come back with. One faded at some times only, a static one and a
    spawned one (its lifespan, not the net) are kept; a transparent static one goes as before."""
    from kgs_core.train.densify import DensifyStrategy

    m = moving_model(seed=3, time_opacity=True)
    m.dynamic[:8] = False  # 0-7 static
    m.lifespan[8] = torch.tensor([0.5, 0.1])  # 8: spawned
    with torch.no_grad():
        m.params.features.normal_(generator=torch.Generator().manual_seed(0))
        head = m.time_opacity.mlp[-1]
        head.weight.zero_()
        head.bias.fill_(-12.0)  # every field-moved Gaussian faded to ~1e-5 of itself at every time
        m.params.opacity_logits.fill_(2.0)  # 0.88 on their own
        m.params.opacity_logits[0] = math.log(0.001 / 0.999)  # a transparent static one
    faded = m.dynamic.clone()
    faded[8] = False
    assert (torch.stack([m.at(t, velocity=False).opacities for t in (0.0, 0.5, 1.0)]).max(0).values[faded] < 0.005).all()
    before = m.params.means.detach().clone()
    DensifyStrategy(grad_threshold=1.0, extent=10.0)._densify_and_prune(m, None)  # no gradients: prune only
    kept = torch.tensor([any(torch.equal(row, k) for k in m.params.means.detach()) for row in before])
    expected = ~faded
    expected[0] = False
    assert torch.equal(kept, expected), (kept, expected)

    # Faded over the first half of the clip only (offset 24 t - 12): it renders later, so it stays.
    m = moving_model(seed=3, time_opacity=True)
    first, last = m.time_opacity.mlp[0], m.time_opacity.mlp[-1]
    with torch.no_grad():
        m.params.opacity_logits.fill_(2.0)
        first.weight[0].zero_()
        first.weight[0, m.config.feature_dim] = 24.0  # hidden unit 0 = relu(24 t): t is gamma(t)'s first entry
        first.bias[0] = 0.0
        last.weight.zero_()
        last.weight[0, 0] = 1.0
        last.bias.fill_(-12.0)
    assert (m.at(0.0, velocity=False).opacities < 0.005).all() and (m.at(1.0, velocity=False).opacities > 0.5).all()
    n = len(m)
    DensifyStrategy(grad_threshold=1.0, extent=10.0)._densify_and_prune(m, None)
    assert len(m) == n


def test_time_opacity_starts_as_the_paper_and_learns_to_fade_a_gaussian_at_one_time_only():
    """`ModelConfig.time_opacity`: zero-initialised, every dynamic Gaussian is as opaque at every
    time as without it; trained, one Gaussian can fade at one time and stay at another; spawned
    Gaussians (a bounded lifespan) and the exact and dynamic-only evaluations agree; a save
    keeps it."""
    plain = moving_model(seed=3)
    m = moving_model(seed=3, time_opacity=True)
    with torch.no_grad():
        assert torch.equal(m.at(0.4, velocity=False).opacities, plain.at(0.4, velocity=False).opacities)
    m.lifespan[5] = torch.tensor([0.5, 0.1])  # one spawned Gaussian: its lifespan, not the net
    before = m.params.opacities.detach().clone()
    with torch.no_grad():  # features as training leaves them: one per Gaussian
        m.params.features.normal_(generator=torch.Generator().manual_seed(0))
    opt = torch.optim.Adam([*m.time_opacity.parameters(), m.params.features], lr=0.02)
    for _ in range(150):
        early, late = m.at(0.2, velocity=False).opacities / before, m.at(0.8, velocity=False).opacities / before
        loss = early[0] + (late[0] - 1) ** 2 + ((early[1:5] - 1) ** 2).sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        early, late = m.at(0.2, velocity=False).opacities, m.at(0.8, velocity=False).opacities
        assert early[0] < 0.2 * before[0] and abs(late[0] - before[0]) < 0.1 * before[0]
        assert torch.allclose(early[1:5], before[1:5], atol=0.05)
        assert float(m.opacity_factor(torch.tensor([5]), 0.2)) == 1.0
        idx, dyn = m.at_dynamic(0.2, velocity=False)
        assert torch.allclose(dyn.opacities, early[idx], atol=1e-6)
        loaded = KinematicsGS.from_state(m.state())
        assert torch.allclose(loaded.at(0.2, velocity=False).opacities, early, atol=1e-6)
        # A LoD level's view (built by hand, sharing the networks) fades it as the model does.
        from kgs_core.run import level_view

        snap = {
            "params": {k: v.detach() for k, v in m.params.items()},
            "dynamic": m.dynamic,
            "K": m.K,
            "lifespan": m.lifespan,
            "own_velocity": m.own_velocity,
            "min_scale": 0.0,
        }
        assert torch.allclose(level_view(m, snap).at(0.2, velocity=False).opacities, early, atol=1e-6)
        # It shares every network the model has, and a view of fewer Gaussians leaves the model's alone.
        few = level_view(
            m,
            {
                **snap,
                "params": {k: v[:3] for k, v in snap["params"].items()},
                "dynamic": m.dynamic[:3],
                "K": m.K[:3],
                "lifespan": m.lifespan[:3],
                "own_velocity": m.own_velocity[:3],
            },
        )
        assert len(few) == 3 and len(m) == len(before) and len(few.at(0.2, velocity=False).opacities) == 3
        assert all(getattr(few, name) is net for name, net in m.named_children() if name != "params")
        assert few.kappa is m.kappa and m.params.means.shape[0] == len(before)
        # A loaded run's model is in eval mode, and so is a view of its levels.
        assert not level_view(m.eval(), snap).training and level_view(m.train(), snap).training


def test_per_gaussian_state_resizes_in_lock_step_and_checks_what_it_loads():
    """Every field of `PerGaussian` follows a prune and a densification alike (a new field added
    to FIELDS is resized with no other change), inherits or takes given rows, and a malformed or
    missing saved field is refused by name; a field absent from an older run gets its fill."""
    from kgs_core.model.per_gaussian import FIELDS, PerGaussian

    pg = PerGaussian.empty(5)
    pg.dynamic[[1, 3]] = True
    pg.K[:] = torch.arange(5.0)
    pg.lifespan[2] = torch.tensor([0.4, 0.1])
    kept = pg.select(torch.tensor([True, True, False, True, False]))
    assert len(kept) == 3 and all(len(v) == 3 for _, v in kept.items())
    assert kept.K.tolist() == [0.0, 1.0, 3.0] and kept.dynamic.tolist() == [False, True, True]
    grown = pg.append(torch.tensor([2, 3]), own_velocity=torch.ones(2, 3))
    assert len(grown) == 7 and set(dict(grown.items())) == set(FIELDS)
    assert torch.equal(grown.lifespan[5], pg.lifespan[2]) and grown.dynamic[6] and grown.own_velocity[5:].eq(1).all()
    state = pg.state()
    assert PerGaussian.from_state(state, 5).K.equal(pg.K)
    old = {k: v for k, v in state.items() if k not in ("lifespan", "own_velocity")}  # saved before those existed
    assert torch.isinf(PerGaussian.from_state(old, 5).lifespan[:, 1]).all()
    with pytest.raises(ValueError, match="'dynamic': expected a bool mask"):
        PerGaussian.from_state({**state, "dynamic": state["dynamic"].float()}, 5)
    with pytest.raises(ValueError, match="'lifespan': expected floats, finite centres and widths > 0"):
        PerGaussian.from_state({**state, "lifespan": torch.zeros(5, 2)}, 5)
    with pytest.raises(ValueError, match="'K': expected 5 rows"):
        PerGaussian.from_state({**state, "K": torch.zeros(4)}, 5)
    with pytest.raises(ValueError, match="no field 'K'"):
        PerGaussian.from_state({k: v for k, v in state.items() if k != "K"}, 5)


def test_setting_a_per_gaussian_field_on_a_shallow_copy_leaves_the_original_alone():
    """The server re-decomposes shallow copies of a served model (run_view.decomposed_copy): a field set on
    the copy must not reach the original through a shared container."""
    import copy

    from kgs_core.model.config import ModelConfig
    from kgs_core.model.dynamic import KinematicsGS
    from kgs_core.model.gaussians import init_from_points

    pts = torch.rand(30, 3).numpy()
    m = KinematicsGS(init_from_points(pts, pts, 1, 16), ModelConfig())
    c = copy.copy(m)
    c.dynamic = torch.ones(30, dtype=torch.bool)
    c.K = torch.full((30,), 2.0)
    assert not m.dynamic.any() and not m.K.any() and c.dynamic.all()
