"""The C++ rasteriser against the PyTorch reference, gradients by float64 gradcheck, and
edge inputs."""

from __future__ import annotations

import pytest
import torch

from kgs_core.render import look_at, rasterize
from kgs_core.render.covariance import covariance_from_quat_scale
from kgs_core.render.random_scene import random_scene
from kgs_core.render.sh import eval_sh, rgb_to_sh0

pytestmark = pytest.mark.usefixtures("ext")


def render_both(scene_kwargs: dict, tensors: dict, grad_seed: int = 0, **kw):
    """Renders with both backends, backpropagates the same random weighting of image,
    alpha and depth, and returns {backend: (Rendered, {name: grad})}."""
    results = {}
    for backend in ("torch", "cpu"):
        leaves = {k: v.detach().clone().requires_grad_(v.is_floating_point()) for k, v in tensors.items()}
        out = rasterize(**scene_kwargs, **leaves, backend=backend, **kw)
        g = torch.Generator().manual_seed(grad_seed)
        dt = out.image.dtype
        loss = (
            (out.image * torch.randn(out.image.shape, generator=g, dtype=dt)).sum()
            + (out.alpha * torch.randn(out.alpha.shape, generator=g, dtype=dt)).sum()
            + (out.depth * torch.randn(out.depth.shape, generator=g, dtype=dt)).sum()
        )
        loss.backward()
        grads = {k: v.grad for k, v in leaves.items() if v.requires_grad}
        grads["means2d"] = out.means2d.grad
        results[backend] = (out, grads)
    return results


def scene_args(s, **over):
    kw = dict(means=s.means, quats=s.quats, scales=s.scales, opacities=s.opacities, colors=s.colors)
    kw.update(over)
    cam = dict(viewmat=s.viewmat, K=s.K, width=s.width, height=s.height)
    return cam, kw


def assert_agree(results, fwd_tol=1e-4, grad_rtol=2e-3):
    (a, ga), (b, gb) = results["torch"], results["cpu"]
    assert torch.equal(a.radii > 0, b.radii > 0)
    # Radii come from float32 covariances computed in a different order: allow rounding.
    assert ((a.radii - b.radii).abs() <= 1 + 1e-5 * a.radii).all()
    for name in ("image", "alpha", "depth"):
        x, y = getattr(a, name), getattr(b, name)
        assert torch.isfinite(y).all(), name
        err = (x - y).abs().max().item()
        assert err <= fwd_tol, f"{name}: max abs error {err:.2e} > {fwd_tol:.0e}"
    for name, g in ga.items():
        h = gb[name]
        assert h is not None and torch.isfinite(h).all(), name
        scale = g.abs().max().item()
        err = (g - h).abs().max().item()
        # An analytically zero gradient (e.g. quaternions of isotropic Gaussians) is rounding
        # noise in both backends: compare against a small absolute floor.
        assert err <= grad_rtol * max(scale, 1e-3), f"grad {name}: {err:.2e} vs scale {scale:.2e}"


@pytest.mark.parametrize("n,w,h,seed,aa", [(200, 48, 40, 0, False), (400, 37, 53, 1, True), (800, 64, 64, 2, False), (60, 17, 16, 3, True)])
def test_cpu_matches_torch_reference(n, w, h, seed, aa):
    s = random_scene(n, w, h, seed=seed)
    cam, kw = scene_args(s, background=torch.tensor([0.2, 0.5, 0.9]))
    assert_agree(render_both(cam, kw, antialiased=aa))


@pytest.mark.parametrize("channels", [1, 4, 7, 8, 20])  # 8+: gradient slots span two vectors
def test_arbitrary_channel_counts(channels):
    s = random_scene(300, 40, 32, seed=4)
    colors = torch.rand(300, channels, generator=torch.Generator().manual_seed(0))
    cam, kw = scene_args(s, colors=colors, background=torch.linspace(0, 1, channels))
    assert_agree(render_both(cam, kw))


def test_full_covariance_input_matches_quaternions():
    s = random_scene(300, 40, 40, seed=5)
    covars = covariance_from_quat_scale(s.quats, s.scales)
    cam, kw = scene_args(s)
    kw.pop("quats"), kw.pop("scales")
    results = render_both(cam, dict(kw, covars=covars))
    assert_agree(results)
    ref = rasterize(**cam, means=s.means, quats=s.quats, scales=s.scales, opacities=s.opacities, colors=s.colors)
    assert (results["cpu"][0].image - ref.image).abs().max() < 1e-5


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_spherical_harmonics(degree):
    s = random_scene(200, 32, 32, seed=6)
    g = torch.Generator().manual_seed(degree)
    sh = 0.3 * torch.randn(200, 16, 3, generator=g)
    cam, kw = scene_args(s, sh_coeffs=sh)
    kw.pop("colors")
    assert_agree(render_both(cam, kw, sh_degree=degree))


def test_sh_degree_zero_reproduces_rgb():
    rgb = torch.rand(10, 3)
    sh = torch.zeros(10, 1, 3)
    sh[:, 0] = rgb_to_sh0(rgb)
    out = eval_sh(sh, torch.randn(10, 3), torch.zeros(3), 0)
    assert torch.allclose(out, rgb, atol=1e-6)


def test_gradcheck_float64():
    s = random_scene(6, 20, 18, seed=7, dtype=torch.float64, overlap=4.0)
    cam = dict(viewmat=s.viewmat, K=s.K, width=s.width, height=s.height)
    opac = (s.opacities * 0.8).clamp(max=0.9)  # away from the 0.99 clamp kink
    bg = torch.tensor([0.1, 0.3, 0.6], dtype=torch.float64)

    def f(means, quats, scales, opacities, colors, background):
        out = rasterize(
            **cam, means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, background=background, backend="cpu"
        )
        return out.image, out.alpha, out.depth

    inputs = [t.clone().requires_grad_(True) for t in (s.means, s.quats, s.scales, opac, s.colors, bg)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_gradcheck_float64_covariance_input():
    s = random_scene(5, 16, 16, seed=8, dtype=torch.float64, overlap=4.0)
    cam = dict(viewmat=s.viewmat, K=s.K, width=s.width, height=s.height)
    covars = covariance_from_quat_scale(s.quats, s.scales)

    def f(means, covars, opacities):
        out = rasterize(**cam, means=means, covars=covars, opacities=opacities, colors=s.colors, antialiased=True, backend="cpu")
        return out.image

    inputs = [t.clone().requires_grad_(True) for t in (s.means, covars, s.opacities * 0.8)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_zero_gaussians_render_background():
    s = random_scene(0, 24, 20, seed=0)
    bg = torch.tensor([0.3, 0.6, 0.9])
    cam, kw = scene_args(s, background=bg)
    results = render_both(cam, kw)
    for out, _ in results.values():
        assert torch.allclose(out.image, bg.expand(20, 24, 3))
        assert (out.alpha == 0).all()


def test_all_behind_camera():
    s = random_scene(100, 32, 32, seed=1)
    behind = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 6.0))  # looks away from the cube
    cam, kw = scene_args(s)
    cam["viewmat"] = behind
    results = render_both(cam, kw)
    for out, grads in results.values():
        assert (out.radii == 0).all()
        assert (out.alpha == 0).all()
        assert all(torch.count_nonzero(g) == 0 for g in grads.values() if g is not None)


def test_gaussians_on_image_border():
    s = random_scene(1, 40, 30, seed=2)
    # Centres on corners, edges and just outside the frame, at depth 3.
    fx, cx, cy = float(s.K[0, 0]), float(s.K[0, 2]), float(s.K[1, 2])
    pix = torch.tensor([[0, 0], [40, 30], [40, 0], [0, 30], [20, -2], [-3, 15], [43, 15], [20, 31], [0.5, 29.5]])
    z = 3.0
    means = torch.stack([(pix[:, 0] - cx) * z / fx, (pix[:, 1] - cy) * z / fx, torch.full((9,), z)], -1)
    means[:, 2] -= 3.0  # camera sits at z = -3
    n = len(means)
    g = torch.Generator().manual_seed(0)
    kw = dict(
        means=means,
        quats=torch.randn(n, 4, generator=g),
        scales=torch.full((n, 3), 0.08),
        opacities=torch.full((n,), 0.8),
        colors=torch.rand(n, 3, generator=g),
    )
    cam = dict(viewmat=s.viewmat, K=s.K, width=40, height=30)
    results = render_both(cam, kw)
    assert_agree(results)
    assert int((results["cpu"][0].radii > 0).sum()) == n  # all touch the frame


@pytest.mark.parametrize("scale", [1e-7, 1e-4, 50.0, 1e4])
def test_huge_and_tiny_scales(scale):
    s = random_scene(50, 32, 32, seed=3)
    cam, kw = scene_args(s, scales=torch.full((50, 3), scale))
    results = render_both(cam, kw, antialiased=scale < 1e-3)
    assert_agree(results, fwd_tol=1e-4, grad_rtol=5e-3)


def test_fully_opaque_stack_terminates():
    n = 60
    means = torch.zeros(n, 3)
    means[:, 2] = torch.linspace(-0.5, 0.5, n)
    s = random_scene(1, 32, 32, seed=0)
    kw = dict(
        means=means,
        quats=torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4),
        scales=torch.full((n, 3), 0.5),
        opacities=torch.ones(n),
        colors=torch.rand(n, 3, generator=torch.Generator().manual_seed(1)),
    )
    cam = dict(viewmat=s.viewmat, K=s.K, width=32, height=32)
    results = render_both(cam, kw)
    assert_agree(results)
    out = results["cpu"][0]
    # The front Gaussian is drawn at alpha 0.99; the next would take T below 1e-4, so the
    # pixel stops there (3DGS semantics) and shows the front colour only.
    assert abs(out.alpha[16, 16, 0].item() - 0.99) < 1e-5
    assert torch.allclose(out.image[16, 16], 0.99 * kw["colors"][0], atol=1e-5)


def test_means2d_gradient_and_absgrad_for_densification():
    s = random_scene(200, 32, 32, seed=9)
    leaves = [t.clone().requires_grad_(True) for t in s.tensors()]
    weights = torch.randn(32, 32, 3, generator=torch.Generator().manual_seed(2))
    grads = {}
    for absgrad in (False, True):
        for t in leaves:
            t.grad = None
        out = rasterize(
            leaves[0],
            leaves[3],
            s.viewmat,
            s.K,
            32,
            32,
            quats=leaves[1],
            scales=leaves[2],
            colors=leaves[4],
            backend="cpu",
            absgrad=absgrad,
        )
        (out.image * weights).sum().backward()
        grads[absgrad] = (out.means2d.grad, [t.grad.clone() for t in leaves])
        assert ("means2d_absgrad" in out.info) == absgrad
    g = grads[True][0]
    assert g is not None and g.shape == (200, 2)
    vis = out.radii > 0
    assert torch.count_nonzero(g[vis]) > 0 and torch.count_nonzero(g[~vis]) == 0
    absg = out.info["means2d_absgrad"]
    # Signed weights make pixel contributions cancel: the sum of |.| is strictly larger.
    assert (absg >= g.abs() - 1e-6).all() and bool((absg > g.abs() + 1e-6).any())
    # Asking for it changes nothing else. (With it the backward runs its general path; without,
    # narrow pairs may take the AVX-512 two-rows path, which sums the same terms in another
    # order: equal up to float rounding at each gradient's scale.)
    for a, b in zip([grads[False][0], *grads[False][1]], [g, *grads[True][1]]):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6 * float(a.abs().max()))
    with pytest.raises(ValueError, match="absgrad"):
        rasterize(
            leaves[0], leaves[3], s.viewmat, s.K, 32, 32, quats=leaves[1], scales=leaves[2], colors=leaves[4], backend="torch", absgrad=True
        )


@pytest.mark.parametrize(
    "bad,match",
    [
        (dict(means=torch.zeros(3, 2)), "means"),
        (dict(quats=torch.zeros(3, 3)), "quats"),
        (dict(colors=torch.zeros(4, 3)), "colors"),
        (dict(background=torch.zeros(2)), "background"),
        (dict(width=0), "image size"),
        (dict(near=-1.0), "near"),
    ],
)
def test_bad_arguments_name_the_field(bad, match):
    kw = dict(
        means=torch.zeros(3, 3),
        quats=torch.ones(3, 4),
        scales=torch.ones(3, 3),
        opacities=torch.ones(3),
        colors=torch.ones(3, 3),
        viewmat=torch.eye(4),
        K=torch.eye(3),
        width=8,
        height=8,
    )
    kw.update(bad)
    with pytest.raises(ValueError, match=match):
        rasterize(**kw)


def test_binning_names_mismatched_inputs():
    """The extension's binning call checks its own inputs (the kernels index with them)."""
    from kgs_core.render import _ext

    ext = _ext.load()
    bbox, radii, depths = torch.zeros(4, 4, dtype=torch.int32), torch.ones(4, dtype=torch.int32), torch.ones(4)
    assert len(ext.bin_gaussians(bbox, radii, depths, 16, 16)) == 4
    with pytest.raises(RuntimeError, match="bbox must be"):
        ext.bin_gaussians(bbox[:3], radii, depths, 16, 16)
    with pytest.raises(RuntimeError, match="depths"):
        ext.bin_gaussians(bbox, radii, depths[:2], 16, 16)
    with pytest.raises(RuntimeError, match="image size"):
        ext.bin_gaussians(bbox, radii, depths, 0, 16)


def test_unknown_backend_rejected():
    s = random_scene(3, 8, 8)
    with pytest.raises(ValueError, match="backend"):
        rasterize(s.means, s.opacities, s.viewmat, s.K, 8, 8, quats=s.quats, scales=s.scales, colors=s.colors, backend="gpu")


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_compiled_sh_matches_reference(degree):
    from kgs_core.render.sh import eval_sh_reference

    g = torch.Generator().manual_seed(degree)
    n = 300
    sh = torch.randn(n, 16, 3, generator=g).requires_grad_(True)  # more bases than the degree uses
    means = torch.randn(n, 3, generator=g)
    means[0] = torch.tensor([0.5, -1.0, 2.0])  # exactly at the camera centre: finite colours
    center = torch.tensor([0.5, -1.0, 2.0])
    weights = torch.randn(n, 3, generator=g)
    got = eval_sh(sh, means, center, degree)
    (g_got,) = torch.autograd.grad((got * weights).sum(), sh)
    ref = eval_sh_reference(sh, means, center, degree)
    (g_ref,) = torch.autograd.grad((ref * weights).sum(), sh)
    assert (ref == 0).any()  # the clamp at 0 is exercised
    assert torch.allclose(got, ref, atol=1e-6) and torch.isfinite(got).all()
    assert torch.allclose(g_got, g_ref, atol=1e-6)
    assert g_got[:, (degree + 1) ** 2 :].abs().sum() == 0


def test_compiled_sh_gradcheck_float64():
    g = torch.Generator().manual_seed(7)
    sh = torch.randn(6, 16, 3, dtype=torch.float64, generator=g).requires_grad_(True)
    means = torch.randn(6, 3, dtype=torch.float64, generator=g)
    assert torch.autograd.gradcheck(lambda c: eval_sh(c, means, torch.zeros(3, dtype=torch.float64), 3), (sh,))


def test_cpu_backend_rejects_images_beyond_its_int16_boxes():
    s = random_scene(3, 8, 8)
    with pytest.raises(RuntimeError, match="image size must be 1..32767"):
        rasterize(s.means, s.opacities, s.viewmat, s.K, 40000, 8, quats=s.quats, scales=s.scales, colors=s.colors, backend="cpu")


def test_extension_compiles_the_vector_path_this_cpu_supports():
    """The float kernels have three SIMD paths (simd.h) that differ several-fold in speed; a
    build flag regression (say, -march=native dropped) would fall back to the generic one
    silently, so the compiled path must be the best the CPU offers."""
    from pathlib import Path

    from kgs_core.render import _ext

    try:
        ext = _ext.load()
    except _ext.ExtensionUnavailable:
        pytest.skip("no C++ compiler")
    cpuinfo = Path("/proc/cpuinfo")
    if not cpuinfo.exists():
        pytest.skip("no /proc/cpuinfo to read the CPU's instruction sets from")
    flags = next((line.split(":", 1)[1].split() for line in cpuinfo.read_text().splitlines() if line.startswith("flags")), [])
    expected = "avx512" if "avx512f" in flags else "avx2" if {"avx2", "fma"} <= set(flags) else "generic"
    assert ext.simd_path() == expected


@pytest.mark.parametrize("source", ["project.cpp", "covariance.cpp"])
def test_per_gaussian_loops_stay_vectorised(source, tmp_path):
    """The projection and covariance loops run over a vector of Gaussians only as long as
    their bodies stay branch-free and their reads unmasked (docs/rasterizer.md); one `if`
    and GCC falls back to scalar code without a word, 3-6x slower. Every loop marked
    `#pragma GCC ivdep` must be reported vectorised with the extension's own flags."""
    import platform
    import shutil
    import subprocess

    from kgs_core.render import _ext

    cxx = shutil.which("g++")
    if cxx is None:
        pytest.skip("no g++: this checks GCC's vectoriser")
    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("the check compiles for x86-64 AVX2")
    path = _ext.CSRC / source
    lines = path.read_text().splitlines()
    loops = [i + 2 for i, line in enumerate(lines) if line.strip().startswith("#pragma GCC ivdep")]
    assert loops, f"no marked loop in {source}"
    flags = [f for f in _ext.CFLAGS if f != "-march=native"] + ["-march=x86-64-v3"]
    report = subprocess.run(
        [cxx, *flags, "-fopt-info-vec-optimized", "-c", str(path), "-o", str(tmp_path / "out.o")],
        capture_output=True,
        text=True,
        check=True,
    ).stderr
    vectorised = {r.split(":")[1] for r in report.splitlines() if "loop vectorized" in r and source in r}
    for line in loops:
        assert str(line) in vectorised, f"{source}:{line} is no longer vectorised"


def test_build_lock_clears_the_lock_file_a_killed_build_left(tmp_path):
    """torch waits forever on the `lock` file of a build that was killed half-way; holding our
    flock, that file can only be stale, so it goes. A second holder waits for the first."""
    import subprocess
    import sys
    import time

    from kgs_core.render._ext import _build_lock

    (tmp_path / "lock").touch()
    with _build_lock(tmp_path):
        assert not (tmp_path / "lock").exists()
        code = (
            "from pathlib import Path; from kgs_core.render._ext import _build_lock\n"
            f"print('waiting', flush=True)\nwith _build_lock(Path({str(tmp_path)!r})): print('held', flush=True)"
        )
        other = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
        assert other.stdout.readline().strip() == "waiting"
        time.sleep(0.5)
        assert other.poll() is None  # still waiting for the flock
    assert other.communicate(timeout=30)[0].strip() == "held" and other.returncode == 0
