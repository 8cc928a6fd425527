"""The paper's K.R. equations (9)-(19) and appendix A.1 (eqs. uz, rref, ux, uy, Rtilde) against
an independent float64 NumPy implementation written from the paper's text, on random
non-diagonal covariances and random velocities, including velocities within the reference
switch's cap around e_x. Each test fails on a wrong equation: a transposed basis, e_z as the
alternative reference, eta without its max, a missing residual."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from kgs_core.model.kinematics import kinematic_basis, refine_covariance

RNG = np.random.default_rng(7)


def paper_basis(v: np.ndarray, eps: float = 1e-8) -> np.ndarray:
    """Appendix A.1: u_z = v / (|v| + eps); r_ref = e_y if |u_z . e_x| > 0.99 else e_x;
    u_x = u_z x r_ref / (|u_z x r_ref| + eps); u_y = u_z x u_x; R~ = [u_x | u_y | u_z]."""
    uz = v / (np.linalg.norm(v) + eps)
    ref = np.array([0.0, 1.0, 0.0]) if abs(uz[0]) > 0.99 else np.array([1.0, 0.0, 0.0])
    ux = np.cross(uz, ref)
    ux /= np.linalg.norm(ux) + eps
    uy = np.cross(uz, ux)
    return np.stack([ux, uy, uz], axis=1)  # columns


def rodrigues(w: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(w)
    if th < 1e-12:
        return np.eye(3)
    k = w / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def paper_refine(sigma, v, blur_len, delta_s, delta_r, r_z, kappa, lambda_s=0.1) -> np.ndarray:
    """Eqs. (9)-(19): sigma_k^2 = u_k^T Sigma u_k; s' = (sigma_x, sigma_y, sigma_z + eta |v| dt);
    eta = max(|r_z . u_z|, sigmoid(kappa)); l_s = log s' + lambda_s ds; S = diag(exp l_s);
    R = R~ exp(dr); Sigma_kin = R S S^T R^T."""
    R_t = paper_basis(v)
    sig = np.sqrt([R_t[:, k] @ sigma @ R_t[:, k] for k in range(3)])
    eta = max(abs(r_z @ R_t[:, 2]), 1 / (1 + np.exp(-kappa)))
    s = np.array([sig[0], sig[1], sig[2] + eta * blur_len])
    S = np.diag(np.exp(np.log(s) + lambda_s * delta_s))
    R = R_t @ rodrigues(delta_r)
    return R @ S @ S.T @ R.T


def random_spd(n: int) -> np.ndarray:
    A = RNG.normal(size=(n, 3, 3)) * 0.05
    return A @ A.transpose(0, 2, 1) + 1e-4 * np.eye(3)


def random_velocities(n: int) -> np.ndarray:
    """Half of them anywhere, half within the switch's cap (|u_z . e_x| > 0.99) or just outside it."""
    v = RNG.normal(size=(n, 3))
    near = v[n // 2 :]
    near[:, 0] = np.sign(RNG.normal(size=len(near))) * 1.0
    near[:, 1:] *= RNG.uniform(0.02, 0.2, size=(len(near), 1))  # |u_z . e_x| from about 0.98 to 0.9998
    v *= RNG.uniform(0.1, 3.0, size=(n, 1))
    return v


def test_the_kinematic_basis_is_appendix_a1_including_the_reference_switch():
    v = random_velocities(400)
    got = kinematic_basis(torch.from_numpy(v), "paper").numpy()
    want = np.stack([paper_basis(x) for x in v])
    switched = np.abs(v[:, 0] / np.linalg.norm(v, axis=1)) > 0.99
    assert 20 < switched.sum() < 180  # both sides of the switch are exercised
    np.testing.assert_allclose(got, want, atol=1e-6)  # (the epsilons differ in form, not in size)
    # columns, not rows: u_z (the third column) is the velocity's direction
    np.testing.assert_allclose(got[:, :, 2], v / np.linalg.norm(v, axis=1, keepdims=True), atol=1e-9)


def test_the_refined_covariance_is_eqs_9_to_19_on_random_non_diagonal_inputs():
    n = 300
    sigma, v = random_spd(n), random_velocities(n)
    dt, exposure = 1 / 30, 0.5
    blur_len = np.linalg.norm(v, axis=1) * dt * exposure
    delta_s, delta_r = RNG.normal(size=(n, 3)), RNG.normal(size=(n, 3)) * 0.3
    r_z = RNG.normal(size=(n, 3))
    r_z /= np.linalg.norm(r_z, axis=1, keepdims=True)
    for kappa in (-6.0, 0.3):  # |r_z . u_z| wins nearly always, then each side of the max for some
        T = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float64))  # noqa: E731
        got = refine_covariance(
            T(sigma), T(v), T(blur_len), T(delta_s), T(delta_r), T(r_z), T(kappa), frame_len=T(np.full(n, 1e9)), basis="paper", lambda_s=0.1
        ).numpy()
        want = np.stack([paper_refine(sigma[i], v[i], blur_len[i], delta_s[i], delta_r[i], r_z[i], kappa) for i in range(n)])
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-9)


def test_the_paper_velocity_is_the_offset_over_the_frame_interval():
    """Eq. (9)'s v = dx_t / dt (`velocity="paper"`, one sample); the physical velocity is the
    central difference of the offsets over +-h."""
    from kgs_core.model.deformation import Offsets
    from kgs_core.model.kinematics import velocity_from_offsets

    g = torch.Generator().manual_seed(3)
    offs = [Offsets.from_cat(torch.randn(20, 9, generator=g, dtype=torch.float64)) for _ in range(3)]
    dt, h = 1 / 60, 1 / 120
    assert torch.allclose(velocity_from_offsets(offs[:1], h, dt), offs[0].dx * 60)
    assert torch.allclose(velocity_from_offsets(offs, h, dt), (offs[1].dx - offs[2].dx) * 60)


def test_coarse_to_fine_offsets_are_the_dynamic_neighbours_mean_of_the_field_plus_the_residual():
    """Eqs. (6)-(8): a dynamic Gaussian's offsets are the mean of the field F_theta over its k
    nearest *dynamic* neighbours (itself included) plus its own fine residual g_phi; static
    Gaussians interleaved with the dynamic ones are no one's neighbours."""
    from scipy.spatial import cKDTree

    from tests.test_model import moving_model

    m = moving_model(n=120, seed=4, knn=6)
    dynamic = torch.zeros(120, dtype=torch.bool)
    dynamic[::2] = True  # every other Gaussian: static ones sit among the dynamic ones
    m.dynamic, m._knn, m._knn_mean = dynamic, None, None
    idx = torch.nonzero(dynamic).squeeze(1)
    t = 0.37
    with torch.no_grad():
        got = m.offsets(idx, t).cat().numpy()
        means = m.params.means.detach()
        field = m.deform.at_times(means[idx], [torch.full((len(idx),), t)])[0].cat().numpy()
        fine = m.fine(m.params.features[idx], torch.full((len(idx),), t)).cat().numpy()
    _, nn = cKDTree(means[idx].numpy()).query(means[idx].numpy(), k=6)
    want = field[nn].mean(1) + fine
    np.testing.assert_allclose(got, want, atol=1e-5)
    # (the check can fail: over all Gaussians the neighbourhoods are others)
    _, nn_all = cKDTree(means.numpy()).query(means[idx].numpy(), k=6)
    assert (np.sort(idx.numpy()[nn], 1) != np.sort(nn_all, 1)).any()


def _trainer(tmp_path, **over):
    """A trainer on the real fixture, decomposed with about half its Gaussians dynamic, no time noise."""
    from pathlib import Path

    from kgs_core.data.formats import load_scene
    from kgs_core.train.config import make_config
    from kgs_core.train.trainer import Trainer

    scene = load_scene(Path(__file__).parent / "fixtures" / "walk96")
    cfg = make_config("fast", iterations=10, noise_init_frames=0.0, lambda_tv=0.0, eval_every=100, checkpoint_every=100, **over)
    tr = Trainer(scene, tmp_path / "run", cfg, progress=False)
    tr.init_model()
    m = tr.model
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():  # a field that moves things (a fresh one's offsets are zero)
        for mlp in (m.deform.mlp, m.fine.mlp):
            mlp[-1].weight.normal_(0, 0.3, generator=g)
        for grid in m.deform.planes.grids:
            grid.add_(0.2 * torch.randn(grid.shape, generator=g))
    m.decompose(tau=1e-12)
    m.dynamic = torch.arange(len(m)) % 2 == 0
    m._knn, m._knn_mean = None, None
    return tr


def test_l_reg_after_a_split_is_both_of_eq_22_terms(tmp_path):
    """Eq. (22): mean |dx| over the dynamic set (their rendered offsets) plus mean |dx| of the
    field over the static set (every static Gaussian when the sample covers them all)."""
    tr = _trainer(tmp_path, lambda_reg=1.0, lambda_ani=0.0, reg_static_samples=10**6)
    frame = tr.scene.train_frames[3]
    m = tr.model
    torch.manual_seed(0)
    with_reg, _ = tr.loss_for(frame, 5)
    tr.cfg = __import__("dataclasses").replace(tr.cfg, lambda_reg=0.0)
    torch.manual_seed(0)
    without, _ = tr.loss_for(frame, 5)
    with torch.no_grad():
        dyn, stat = torch.nonzero(m.dynamic).squeeze(1), torch.nonzero(~m.dynamic).squeeze(1)
        dynamic_term = m.offsets(dyn, frame.time).dx.norm(dim=-1).mean()
        field = m.deform.at_times(m.params.means[stat], [torch.full((len(stat),), frame.time)])[0].dx
        static_term = field.norm(dim=-1).mean()
    assert static_term > 1e-4 and dynamic_term > 1e-4  # both terms carry weight
    assert float((with_reg - without).detach()) == pytest.approx(float(dynamic_term + static_term), rel=1e-4)


def test_l_ani_is_eq_23_on_the_scales_it_acts_on(tmp_path):
    """Eq. (23): mean of max(s) / (min(s) + eps_ani) over every Gaussian's scales."""
    tr = _trainer(tmp_path, lambda_reg=0.0, lambda_ani=1.0, eps_ani=1e-3)
    frame = tr.scene.train_frames[2]
    with torch.no_grad():
        tr.model.params.log_scales.add_(torch.randn_like(tr.model.params.log_scales))  # anisotropic
    torch.manual_seed(0)
    with_ani, _ = tr.loss_for(frame, 5)
    tr.cfg = __import__("dataclasses").replace(tr.cfg, lambda_ani=0.0)
    torch.manual_seed(0)
    without, _ = tr.loss_for(frame, 5)
    s = tr.model.params.log_scales.detach().exp()
    want = (s.max(-1).values / (s.min(-1).values + 1e-3)).mean()
    assert float((with_ani - without).detach()) == pytest.approx(float(want), rel=1e-4)


def test_flod_minimum_scale_decays_geometrically_to_none_at_the_top_level(tmp_path):
    """Eq. (3) as we read it (docs/method.md: the exponent's sign flipped so that levels go coarse
    to fine): s_min(l) = lambda rho^(l-1) for l < L_max, 0 at L_max."""
    tr = _trainer(tmp_path, lod_levels=5, lod_fractions=(0.1, 0.2, 0.35, 0.55, 1.0), lod_lambda=0.02, lod_rho=0.5)
    assert [tr.level_min_scale(i) for i in range(5)] == pytest.approx([0.02, 0.01, 0.005, 0.0025, 0.0])


@pytest.mark.parametrize("inputs", ["predicted", "canonical"])
def test_the_paper_form_reads_the_inputs_the_paper_names(tmp_path, inputs):
    """`kr_inputs="predicted"` (the paper preset): eqs. 9-19 take Σ, the covariance the field
    predicts (R(q) exp(δr), s exp(λ_s δs)), and r_z, the principal axis of that predicted
    rotation, with v = δx_t / Δt and no blend toward Σ when slow; "canonical" takes the canonical
    Σ and axis. Checked against the independent implementation at every dynamic Gaussian, and
    each against the other's inputs (so a model that ignored `kr_inputs` fails one case)."""
    over = {"model.kr_form": "paper", "model.kr_inputs": inputs, "model.velocity": "paper", "model.still_len": 0.0}
    tr = _trainer(tmp_path, **over)
    m, t, dt, e = tr.model, 0.4, 1 / 30, 0.5
    with torch.no_grad():
        got = m.at(t, exposure=e, dt=dt)
        dyn = torch.nonzero(m.dynamic).squeeze(1)
        off = m.offsets(dyn, t)
        R0 = Rotation.from_quat(m.params.quats[dyn].double().numpy()[:, [1, 2, 3, 0]]).as_matrix()  # scipy: xyzw
        s0 = m.scales()[dyn].double().numpy()
        kappa = float(m.kappa)
    dx, dr, ds = (x.double().numpy() for x in (off.dx, off.dr, off.ds))
    want = {"predicted": [], "canonical": []}
    for i in range(len(dyn)):
        v = dx[i] / dt
        R_pred, s_pred = R0[i] @ rodrigues(dr[i]), s0[i] * np.exp(0.1 * ds[i])
        for name, (R, s) in {"predicted": (R_pred, s_pred), "canonical": (R0[i], s0[i])}.items():
            sigma = R @ np.diag(s**2) @ R.T
            want[name].append(paper_refine(sigma, v, np.linalg.norm(v) * dt * e, ds[i], dr[i], R[:, np.argmax(s)], kappa))
    cov = got.covars[dyn].double().numpy()
    other = "canonical" if inputs == "predicted" else "predicted"
    np.testing.assert_allclose(cov, np.stack(want[inputs]), rtol=2e-3, atol=1e-9)
    assert np.abs(cov - np.stack(want[other])).max() > 100 * np.abs(cov - np.stack(want[inputs])).max()
