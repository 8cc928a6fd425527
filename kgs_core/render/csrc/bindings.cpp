// Torch bindings: check shapes and dtypes, allocate outputs, dispatch float/double.
#include <torch/extension.h>

#include "kernels.h"
#include "simd.h"

namespace {

using torch::Tensor;

void check(const Tensor& t, const char* name, c10::ScalarType dtype) {
  TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
  TORCH_CHECK(t.scalar_type() == dtype, name, " has dtype ", t.scalar_type(), ", expected ", dtype);
}

kgs::Camera make_camera(const Tensor& viewmat, const Tensor& K, int64_t width, int64_t height,
                        double near_plane, double far_plane) {
  TORCH_CHECK(viewmat.sizes() == torch::IntArrayRef({4, 4}), "viewmat must be (4, 4)");
  TORCH_CHECK(K.sizes() == torch::IntArrayRef({3, 3}), "K must be (3, 3)");
  const auto vm = viewmat.to(torch::kFloat64).contiguous();
  const auto kk = K.to(torch::kFloat64).contiguous();
  kgs::Camera cam;
  std::copy(vm.data_ptr<double>(), vm.data_ptr<double>() + 16, cam.viewmat);
  const double* kp = kk.data_ptr<double>();
  cam.fx = kp[0]; cam.cx = kp[2]; cam.fy = kp[4]; cam.cy = kp[5];
  cam.width = int(width); cam.height = int(height);
  cam.near_plane = near_plane; cam.far_plane = far_plane;
  return cam;
}

Tensor covar_forward(Tensor quats, Tensor scales) {
  const auto dt = quats.scalar_type();
  check(quats, "quats", dt);
  check(scales, "scales", dt);
  const int64_t n = quats.size(0);
  TORCH_CHECK(quats.dim() == 2 && quats.size(1) == 4, "quats must be (N, 4)");
  TORCH_CHECK(scales.dim() == 2 && scales.size(0) == n && scales.size(1) == 3, "scales must be (N, 3)");
  auto cov6 = torch::empty({n, 6}, quats.options());
  AT_DISPATCH_FLOATING_TYPES(dt, "covar_forward", [&] {
    kgs::covar_forward<scalar_t>(n, quats.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(),
                                 cov6.data_ptr<scalar_t>());
  });
  return cov6;
}

std::vector<Tensor> covar_backward(Tensor quats, Tensor scales, Tensor g_cov6) {
  const auto dt = quats.scalar_type();
  check(g_cov6, "g_cov6", dt);
  auto g_quats = torch::empty_like(quats), g_scales = torch::empty_like(scales);
  AT_DISPATCH_FLOATING_TYPES(dt, "covar_backward", [&] {
    kgs::covar_backward<scalar_t>(quats.size(0), quats.data_ptr<scalar_t>(),
                                  scales.data_ptr<scalar_t>(), g_cov6.data_ptr<scalar_t>(),
                                  g_quats.data_ptr<scalar_t>(), g_scales.data_ptr<scalar_t>());
  });
  return {g_quats, g_scales};
}

std::vector<Tensor> project_forward(Tensor means, Tensor covars, Tensor opacities, Tensor viewmat,
                                    Tensor K, int64_t width, int64_t height, double near_plane,
                                    double far_plane, double eps2d, bool antialiased) {
  const auto dt = means.scalar_type();
  check(means, "means", dt); check(covars, "covars", dt); check(opacities, "opacities", dt);
  const int64_t n = means.size(0);
  TORCH_CHECK(covars.size(0) == n && covars.size(1) == 6, "covars must be (N, 6)");
  const auto cam = make_camera(viewmat, K, width, height, near_plane, far_plane);
  auto opts = means.options();
  auto means2d = torch::empty({n, 2}, opts), conics = torch::empty({n, 3}, opts);
  auto depths = torch::empty({n}, opts), opac_eff = torch::empty({n}, opts);
  auto radii = torch::empty({n}, opts.dtype(torch::kInt32));
  auto bbox = torch::empty({n, 4}, opts.dtype(torch::kInt32));
  AT_DISPATCH_FLOATING_TYPES(dt, "project_forward", [&] {
    kgs::project_forward<scalar_t>(n, means.data_ptr<scalar_t>(), covars.data_ptr<scalar_t>(),
                                   opacities.data_ptr<scalar_t>(), cam, scalar_t(eps2d),
                                   antialiased, means2d.data_ptr<scalar_t>(),
                                   conics.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(),
                                   opac_eff.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(),
                                   bbox.data_ptr<int32_t>());
  });
  return {means2d, conics, depths, opac_eff, radii, bbox};
}

// Motion-blur footprint factor: means (B, 3), packed blurred covariances (B, 6), sweeps (B, 3).
void check_blur(const Tensor& means, const Tensor& covars, const Tensor& sweeps) {
  const auto dt = means.scalar_type();
  check(means, "blur means", dt); check(covars, "blur covariances", dt); check(sweeps, "blur sweeps", dt);
  const int64_t n = means.size(0);
  TORCH_CHECK(means.dim() == 2 && means.size(1) == 3, "blur: means must be (B, 3)");
  TORCH_CHECK(covars.dim() == 2 && covars.size(0) == n && covars.size(1) == 6, "blur: covariances must be (B, 6)");
  TORCH_CHECK(sweeps.dim() == 2 && sweeps.size(0) == n && sweeps.size(1) == 3, "blur: sweeps must be (B, 3)");
}

Tensor blur_scale_forward(Tensor means, Tensor covars, Tensor sweeps, Tensor viewmat, Tensor K, int64_t width,
                          int64_t height, double near_plane, double far_plane, double eps2d) {
  check_blur(means, covars, sweeps);
  const auto cam = make_camera(viewmat, K, width, height, near_plane, far_plane);
  auto scale = torch::empty({means.size(0)}, means.options());
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "blur_scale_forward", [&] {
    kgs::blur_scale_forward<scalar_t>(means.size(0), means.data_ptr<scalar_t>(), covars.data_ptr<scalar_t>(),
                                      sweeps.data_ptr<scalar_t>(), cam, scalar_t(eps2d), scale.data_ptr<scalar_t>());
  });
  return scale;
}

// -> [g_covars (B, 6), g_sweeps (B, 3)]
std::vector<Tensor> blur_scale_backward(Tensor means, Tensor covars, Tensor sweeps, Tensor viewmat, Tensor K,
                                        int64_t width, int64_t height, double near_plane, double far_plane,
                                        double eps2d, Tensor g_scale) {
  check_blur(means, covars, sweeps);
  check(g_scale, "blur gradient", means.scalar_type());
  TORCH_CHECK(g_scale.dim() == 1 && g_scale.size(0) == means.size(0), "blur: gradient must be (B,)");
  const auto cam = make_camera(viewmat, K, width, height, near_plane, far_plane);
  auto g_cov = torch::empty_like(covars), g_sweep = torch::empty_like(sweeps);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "blur_scale_backward", [&] {
    kgs::blur_scale_backward<scalar_t>(means.size(0), means.data_ptr<scalar_t>(), covars.data_ptr<scalar_t>(),
                                       sweeps.data_ptr<scalar_t>(), cam, scalar_t(eps2d),
                                       g_scale.data_ptr<scalar_t>(), g_cov.data_ptr<scalar_t>(),
                                       g_sweep.data_ptr<scalar_t>());
  });
  return {g_cov, g_sweep};
}

std::vector<Tensor> project_backward(Tensor means, Tensor covars, Tensor opacities,
                                     Tensor viewmat, Tensor K, int64_t width, int64_t height,
                                     double near_plane, double far_plane, double eps2d,
                                     bool antialiased, Tensor radii, Tensor g_means2d,
                                     Tensor g_conics, Tensor g_depths, Tensor g_opac_eff) {
  const auto dt = means.scalar_type();
  check(radii, "radii", torch::kInt32);
  for (auto* t : {&g_means2d, &g_conics, &g_depths, &g_opac_eff}) check(*t, "gradient", dt);
  const int64_t n = means.size(0);
  const auto cam = make_camera(viewmat, K, width, height, near_plane, far_plane);
  auto g_means = torch::empty_like(means), g_covars = torch::empty_like(covars);
  auto g_opac = torch::empty_like(opacities);
  AT_DISPATCH_FLOATING_TYPES(dt, "project_backward", [&] {
    kgs::project_backward<scalar_t>(
        n, means.data_ptr<scalar_t>(), covars.data_ptr<scalar_t>(),
        opacities.data_ptr<scalar_t>(), cam, scalar_t(eps2d), antialiased,
        radii.data_ptr<int32_t>(), g_means2d.data_ptr<scalar_t>(), g_conics.data_ptr<scalar_t>(),
        g_depths.data_ptr<scalar_t>(), g_opac_eff.data_ptr<scalar_t>(),
        g_means.data_ptr<scalar_t>(), g_covars.data_ptr<scalar_t>(), g_opac.data_ptr<scalar_t>());
  });
  return {g_means, g_covars, g_opac};
}

kgs::RasterShape shape_of(int64_t width, int64_t height, int64_t channels) {
  // The per-Gaussian lines of raster.cpp store bounding boxes as int16.
  TORCH_CHECK(width >= 1 && height >= 1 && width <= 32767 && height <= 32767,
              "image size must be 1..32767 pixels per side, got ", width, "x", height);
  return {int(width), int(height), int(channels), int((width + kgs::TILE - 1) / kgs::TILE),
          int((height + kgs::TILE - 1) / kgs::TILE)};
}

// Returns (tile_offsets, tile_ranks, order, id_start): see kernels.h. The boxes are the
// projection's, clipped to the image; they are not checked again here.
std::vector<Tensor> bin_gaussians(Tensor bbox, Tensor radii, Tensor depths, int64_t width,
                                  int64_t height) {
  const auto shape = shape_of(width, height, 1);  // with the size checks
  check(bbox, "bbox", torch::kInt32);
  check(radii, "radii", torch::kInt32);
  check(depths, "depths", depths.scalar_type());
  const int64_t n = radii.size(0);
  TORCH_CHECK(bbox.numel() == 4 * n && depths.numel() == n, "bbox must be (N, 4) and depths (N,)");
  const int64_t tiles = int64_t(shape.tiles_x) * shape.tiles_y;
  auto opts = bbox.options();
  auto offsets = torch::empty({tiles + 1}, opts), id_start = torch::empty({n + 1}, opts);
  Tensor order, ranks;
  auto allocate = [&](int64_t n_visible, int64_t pairs) {
    TORCH_CHECK(pairs < (int64_t(1) << 31), "too many tile/Gaussian pairs: ", pairs);
    order = torch::empty({n_visible}, opts);
    ranks = torch::empty({pairs}, opts);
    return kgs::BinOutputs{offsets.data_ptr<int32_t>(), order.data_ptr<int32_t>(), ranks.data_ptr<int32_t>(),
                           id_start.data_ptr<int32_t>()};
  };
  AT_DISPATCH_FLOATING_TYPES(depths.scalar_type(), "bin_gaussians", [&] {
    kgs::bin_gaussians<scalar_t>(n, bbox.data_ptr<int32_t>(), radii.data_ptr<int32_t>(),
                                 depths.data_ptr<scalar_t>(), int(width), int(height), allocate);
  });
  return {offsets, ranks, order, id_start};
}

kgs::TileLists lists_of(const Tensor& offsets, const Tensor& ranks, const Tensor& order,
                        const Tensor& id_start, int64_t n, const kgs::RasterShape& shape) {
  check(offsets, "tile_offsets", torch::kInt32);
  check(ranks, "tile_ranks", torch::kInt32);
  check(order, "order", torch::kInt32);
  check(id_start, "id_start", torch::kInt32);
  const int64_t tiles = int64_t(shape.tiles_x) * shape.tiles_y;
  TORCH_CHECK(offsets.numel() == tiles + 1, "tile_offsets does not match the image size");
  TORCH_CHECK(id_start.numel() == n + 1, "id_start must have one entry per Gaussian, plus one");
  const int64_t n_pairs = offsets.data_ptr<int32_t>()[tiles];
  TORCH_CHECK(ranks.numel() == n_pairs, "tile_ranks must have one entry per pair");
  TORCH_CHECK(id_start.data_ptr<int32_t>()[n] == n_pairs, "id_start does not number the pairs");
  return {order.numel(), n_pairs, order.data_ptr<int32_t>(), offsets.data_ptr<int32_t>(),
          ranks.data_ptr<int32_t>(), id_start.data_ptr<int32_t>()};
}

std::vector<Tensor> raster_forward(Tensor means2d, Tensor conics, Tensor opac, Tensor colors,
                                   Tensor depths, Tensor bbox, Tensor background,
                                   Tensor tile_offsets, Tensor tile_ranks, Tensor order,
                                   Tensor id_start, int64_t width,
                                   int64_t height) {
  const auto dt = means2d.scalar_type();
  for (auto* t : {&means2d, &conics, &opac, &colors, &depths, &background}) check(*t, "raster input", dt);
  check(bbox, "bbox", torch::kInt32);
  const int64_t C = colors.size(1);
  TORCH_CHECK(background.numel() == C, "background must have ", C, " channels");
  const auto shape = shape_of(width, height, C);
  const int64_t n = means2d.size(0);
  const auto lists = lists_of(tile_offsets, tile_ranks, order, id_start, n, shape);
  auto opts = means2d.options();
  auto records = torch::empty({lists.n_pairs, kgs::RECORD_HEAD + C}, opts);
  auto image = torch::empty({height, width, C}, opts);
  auto alpha = torch::empty({height, width}, opts), depth = torch::empty({height, width}, opts);
  auto t_final = torch::empty({height, width}, opts);
  auto n_contrib = torch::empty({height, width}, opts.dtype(torch::kInt32));
  AT_DISPATCH_FLOATING_TYPES(dt, "raster_forward", [&] {
    kgs::raster_forward<scalar_t>(
        shape, lists, n, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
        opac.data_ptr<scalar_t>(), colors.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(),
        bbox.data_ptr<int32_t>(), background.data_ptr<scalar_t>(), records.data_ptr<scalar_t>(),
        image.data_ptr<scalar_t>(), alpha.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(),
        t_final.data_ptr<scalar_t>(), n_contrib.data_ptr<int32_t>());
  });
  return {image, alpha, depth, t_final, n_contrib, records};
}

std::vector<Tensor> raster_backward(Tensor records, Tensor background, Tensor tile_offsets,
                                    Tensor tile_ranks, Tensor order, Tensor id_start,
                                    Tensor t_final, Tensor n_contrib, Tensor g_image,
                                    Tensor g_alpha, Tensor g_depth, int64_t n, int64_t width,
                                    int64_t height, bool absgrad) {
  const auto dt = records.scalar_type();
  for (auto* t : {&records, &background, &t_final, &g_image}) check(*t, "raster backward input", dt);
  // The alpha and depth gradients may be empty: those outputs took no part in the loss.
  for (auto* t : {&g_alpha, &g_depth}) {
    if (t->numel() == 0) continue;
    check(*t, "raster backward input", dt);
    TORCH_CHECK(t->numel() == t_final.numel(), "alpha and depth gradients must be (H, W)");
  }
  check(n_contrib, "n_contrib", torch::kInt32);
  const int64_t C = background.numel();
  const auto shape = shape_of(width, height, C);
  const auto lists = lists_of(tile_offsets, tile_ranks, order, id_start, n, shape);
  TORCH_CHECK(records.dim() == 2 && records.size(0) == lists.n_pairs && records.size(1) == kgs::RECORD_HEAD + C,
              "records do not match the tile lists");
  auto opts = records.options();
  auto g_means2d = torch::empty({n, 2}, opts), g_conics = torch::empty({n, 3}, opts);
  auto g_opac = torch::empty({n}, opts), g_colors = torch::empty({n, C}, opts);
  auto g_depths = torch::empty({n}, opts), abs_g = torch::empty({n, 2}, opts);
  AT_DISPATCH_FLOATING_TYPES(dt, "raster_backward", [&] {
    kgs::raster_backward<scalar_t>(
        shape, lists, n, records.data_ptr<scalar_t>(), background.data_ptr<scalar_t>(),
        t_final.data_ptr<scalar_t>(), n_contrib.data_ptr<int32_t>(), g_image.data_ptr<scalar_t>(),
        g_alpha.numel() ? g_alpha.data_ptr<scalar_t>() : nullptr,
        g_depth.numel() ? g_depth.data_ptr<scalar_t>() : nullptr, g_means2d.data_ptr<scalar_t>(),
        g_conics.data_ptr<scalar_t>(), g_opac.data_ptr<scalar_t>(), g_colors.data_ptr<scalar_t>(),
        g_depths.data_ptr<scalar_t>(), abs_g.data_ptr<scalar_t>(), absgrad);
  });
  return {g_means2d, g_conics, g_opac, g_colors, g_depths, abs_g};
}

void check_sh(const Tensor& coeffs, const Tensor& means, const Tensor& center, int64_t degree) {
  const auto dt = coeffs.scalar_type();
  check(coeffs, "sh_coeffs", dt);
  check(means, "means", dt);
  check(center, "camera centre", dt);
  TORCH_CHECK(degree >= 0 && degree <= 3, "sh_degree must be in 0..3");
  TORCH_CHECK(coeffs.dim() == 3 && coeffs.size(2) == 3 && coeffs.size(1) >= (degree + 1) * (degree + 1),
              "sh_coeffs must be (N, K >= (degree+1)^2, 3)");
  TORCH_CHECK(means.dim() == 2 && means.size(0) == coeffs.size(0) && means.size(1) == 3, "means must be (N, 3)");
  TORCH_CHECK(center.numel() == 3, "camera centre must have 3 values");
}

Tensor sh_forward(Tensor coeffs, Tensor means, Tensor center, int64_t degree) {
  check_sh(coeffs, means, center, degree);
  auto rgb = torch::empty({coeffs.size(0), 3}, coeffs.options());
  AT_DISPATCH_FLOATING_TYPES(coeffs.scalar_type(), "sh_forward", [&] {
    kgs::sh_forward<scalar_t>(coeffs.size(0), int(coeffs.size(1)), int(degree), coeffs.data_ptr<scalar_t>(),
                              means.data_ptr<scalar_t>(), center.data_ptr<scalar_t>(), rgb.data_ptr<scalar_t>());
  });
  return rgb;
}

Tensor sh_backward(Tensor coeffs, Tensor means, Tensor center, int64_t degree, Tensor g_rgb) {
  check_sh(coeffs, means, center, degree);
  check(g_rgb, "sh colour gradient", coeffs.scalar_type());
  auto g = torch::empty_like(coeffs);
  AT_DISPATCH_FLOATING_TYPES(coeffs.scalar_type(), "sh_backward", [&] {
    kgs::sh_backward<scalar_t>(coeffs.size(0), int(coeffs.size(1)), int(degree), coeffs.data_ptr<scalar_t>(),
                               means.data_ptr<scalar_t>(), center.data_ptr<scalar_t>(), g_rgb.data_ptr<scalar_t>(),
                               g.data_ptr<scalar_t>());
  });
  return g;
}

std::vector<Tensor> ssim_forward(Tensor x, Tensor y, Tensor window) {
  const auto dt = x.scalar_type();
  check(x, "img", dt);
  check(y, "ref", dt);
  check(window, "window", dt);
  TORCH_CHECK(x.dim() == 3 && x.sizes() == y.sizes(), "ssim: img and ref must be equal (H, W, C)");
  const int64_t H = x.size(0), W = x.size(1), C = x.size(2), k = window.numel();
  TORCH_CHECK(k >= 1 && k <= H && k <= W, "ssim: window larger than the image");
  auto maps = torch::empty({5, H - k + 1, W - k + 1, C}, x.options());
  auto out = torch::empty({}, x.options());
  AT_DISPATCH_FLOATING_TYPES(dt, "ssim_forward", [&] {
    out.fill_(kgs::ssim_forward<scalar_t>(x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), int(H), int(W),
                                         int(C), window.data_ptr<scalar_t>(), int(k), maps.data_ptr<scalar_t>()));
  });
  return {out, maps};
}

Tensor ssim_backward(Tensor x, Tensor y, Tensor window, Tensor maps, double grad) {
  const auto dt = x.scalar_type();
  for (auto* t : {&x, &y, &window, &maps}) check(*t, "ssim backward input", dt);
  const int64_t H = x.size(0), W = x.size(1), C = x.size(2), k = window.numel();
  TORCH_CHECK(maps.dim() == 4 && maps.size(0) == 5 && maps.size(1) == H - k + 1 && maps.size(2) == W - k + 1,
              "ssim: maps do not match the image");
  auto g = torch::empty_like(x);
  AT_DISPATCH_FLOATING_TYPES(dt, "ssim_backward", [&] {
    kgs::ssim_backward<scalar_t>(x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), int(H), int(W), int(C),
                                 window.data_ptr<scalar_t>(), int(k), maps.data_ptr<scalar_t>(),
                                 scalar_t(grad), g.data_ptr<scalar_t>());
  });
  return g;
}

// One resolution's six planes (F, H, W) as the kernel's channels-last views; `keep` holds the
// transposed copies alive.
kgs::KPlanes kplanes_views(const std::vector<Tensor>& grids, int64_t r, std::vector<Tensor>& keep) {
  kgs::KPlanes p;
  p.F = grids[0].size(0);
  for (int k = 0; k < 6; ++k) {
    const Tensor& g = grids[r * 6 + k];
    keep.push_back(g.permute({1, 2, 0}).contiguous());
    p.data[k] = keep.back().data_ptr<float>();
    p.grad[k] = nullptr;
    p.H[k] = g.size(1);
    p.W[k] = g.size(2);
  }
  return p;
}

void check_kplanes(const Tensor& x, const Tensor& t, const std::vector<Tensor>& grids) {
  check(x, "kplanes x", torch::kFloat32);
  check(t, "kplanes t", torch::kFloat32);
  TORCH_CHECK(x.dim() == 2 && x.size(1) == 3 && x.size(0) > 0, "kplanes: x must be (N, 3), N > 0");
  TORCH_CHECK(t.dim() == 1 && t.size(0) % x.size(0) == 0, "kplanes: t must be (M N,)");
  TORCH_CHECK(!grids.empty() && grids.size() % 6 == 0, "kplanes: six planes per resolution");
  for (const auto& g : grids)
    TORCH_CHECK(g.dim() == 3 && g.scalar_type() == torch::kFloat32 && g.size(0) == grids[0].size(0) &&
                    g.size(1) >= 1 && g.size(2) >= 1,
                "kplanes: planes must be float32 (F, H, W) with one F");
  TORCH_CHECK(grids[0].size(0) <= 256, "kplanes: at most 256 features per plane");
}

// x (N, 3) and t (M N,) normalised to [-1, 1]; grids: R x 6 planes (F, H, W) -> (M N, F R).
Tensor kplanes_forward(Tensor x, Tensor t, std::vector<Tensor> grids) {
  check_kplanes(x, t, grids);
  const int64_t F = grids[0].size(0), R = int64_t(grids.size()) / 6;
  auto out = torch::empty({t.size(0), F * R}, x.options());
  for (int64_t r = 0; r < R; ++r) {
    std::vector<Tensor> keep;
    kgs::kplanes_forward(x.size(0), t.size(0), x.data_ptr<float>(), t.data_ptr<float>(), kplanes_views(grids, r, keep),
                         out.data_ptr<float>() + r * F, F * R);
  }
  return out;
}

// -> [g_x (N, 3) (zeros unless need_x_grad), g_grid for each plane (F, H, W)].
std::vector<Tensor> kplanes_backward(Tensor x, Tensor t, std::vector<Tensor> grids, Tensor g_out, bool need_x_grad) {
  check_kplanes(x, t, grids);
  const int64_t N = x.size(0), rows = t.size(0), F = grids[0].size(0), R = int64_t(grids.size()) / 6;
  g_out = g_out.contiguous();
  check(g_out, "kplanes gradient", torch::kFloat32);
  TORCH_CHECK(g_out.dim() == 2 && g_out.size(0) == rows && g_out.size(1) == F * R, "kplanes: gradient must be (M N, F R)");
  auto g_x = torch::zeros({N, 3}, x.options());
  std::vector<Tensor> result(1 + grids.size());
  for (int64_t r = 0; r < R; ++r) {
    std::vector<Tensor> keep, acc;
    kgs::KPlanes p = kplanes_views(grids, r, keep);
    for (int k = 0; k < 6; ++k) {
      acc.push_back(torch::zeros({p.H[k], p.W[k], F}, x.options()));
      p.grad[k] = acc.back().data_ptr<float>();
    }
    kgs::kplanes_backward(N, rows, x.data_ptr<float>(), t.data_ptr<float>(), p, g_out.data_ptr<float>() + r * F, F * R,
                          need_x_grad ? g_x.data_ptr<float>() : nullptr);
    for (int k = 0; k < 6; ++k) result[1 + r * 6 + k] = acc[k].permute({2, 0, 1}).contiguous();
  }
  result[0] = g_x;
  return result;
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "Kinematics-GS CPU Gaussian rasteriser";
  m.def("covar_forward", &covar_forward);
  m.def("covar_backward", &covar_backward);
  m.def("project_forward", &project_forward);
  m.def("project_backward", &project_backward);
  m.def("blur_scale_forward", &blur_scale_forward);
  m.def("blur_scale_backward", &blur_scale_backward);
  m.def("bin_gaussians", &bin_gaussians);
  m.def("raster_forward", &raster_forward);
  m.def("raster_backward", &raster_backward);
  m.def("sh_forward", &sh_forward);
  m.def("sh_backward", &sh_backward);
  m.def("ssim_forward", &ssim_forward);
  m.def("ssim_backward", &ssim_backward);
  m.def("kplanes_forward", &kplanes_forward);
  m.def("kplanes_backward", &kplanes_backward);
  // Which float SIMD path simd.h compiled for this CPU: "avx512", "avx2" or "generic".
  m.def("simd_path", [] { return std::string(kgs::SIMD_FLOAT); });
  m.attr("TILE") = kgs::TILE;
}
