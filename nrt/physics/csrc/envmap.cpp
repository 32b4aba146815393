// Fused CPU kernels of the environment map (nrt/physics/envmap.py): the bilinear lookup
// E(d), the sampler's density pdf(d) and its draws of look directions, each in one pass
// instead of the PyTorch path's chain of atan2 / acos / floor / gather ops (every op a
// tensor of the directions' size). Built at first use by nrt/physics/fused_envmap.py.
//
// The arithmetic is the PyTorch path's, operation by operation and in the same dtype
// (the lookup in the map's, the density in the directions', the draws in float64): the
// values agree up to the last bit of atan2 / acos, whose vectorised and scalar forms may
// round differently.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr int64_t kGrain = 2048;  // directions per task at least
constexpr double kPi = 3.14159265358979323846;

// Texture coordinates of a unit look direction: u = atan2(d_x, -d_z) / (2 pi) mod 1,
// v = acos(d_y) / pi (direction_to_uv).
template <typename scalar_t>
inline void to_uv(const scalar_t* d, scalar_t& u, scalar_t& v) {
  u = std::atan2(d[0], -d[2]) / static_cast<scalar_t>(2.0 * kPi);
  u = u - std::floor(u);
  const scalar_t y = std::min(scalar_t(1), std::max(d[1], scalar_t(-1)));
  v = std::acos(y) / static_cast<scalar_t>(kPi);
}

void check_dirs(const at::Tensor& d, const char* what) {
  TORCH_CHECK(d.device().is_cpu() && d.is_contiguous() && d.dim() == 2 && d.size(1) == 3,
              what, ": the directions must be a contiguous CPU tensor (N, 3)");
}

// EnvironmentMap.lookup: Mitsuba's bilinear lookup of radiance (H, W, 3) at look
// directions (N, 3) of the map's dtype; column i centred at u = (i + 0.5) / W with
// wrap-around, row j at v = j / (H - 1).
at::Tensor lookup(const at::Tensor& radiance, const at::Tensor& d) {
  check_dirs(d, "envmap lookup");
  TORCH_CHECK(radiance.device().is_cpu() && radiance.is_contiguous() && radiance.dim() == 3 &&
                  radiance.size(2) == 3 && radiance.scalar_type() == d.scalar_type(),
              "envmap lookup: the map must be a contiguous CPU tensor (H, W, 3) of the "
              "directions' dtype");
  const int64_t h = radiance.size(0), w = radiance.size(1), n = d.size(0);
  at::Tensor out = at::empty({n, 3}, d.options());
  AT_DISPATCH_FLOATING_TYPES(d.scalar_type(), "envmap_lookup", [&] {
    const scalar_t* img = radiance.data_ptr<scalar_t>();
    const scalar_t* dp = d.data_ptr<scalar_t>();
    scalar_t* op = out.data_ptr<scalar_t>();
    const scalar_t half_texel = static_cast<scalar_t>(0.5 / static_cast<double>(w));
    const scalar_t fw = static_cast<scalar_t>(w), rows = static_cast<scalar_t>(h - 1);
    at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) {
        scalar_t u, v;
        to_uv(dp + 3 * i, u, v);
        scalar_t x = u - half_texel;
        x = (x - std::floor(x)) * fw;
        const scalar_t y = v * rows;
        const scalar_t x0 = std::min(fw - 1, std::max(std::floor(x), scalar_t(0)));
        const scalar_t y0 = std::min(rows - 1, std::max(std::floor(y), scalar_t(0)));
        const scalar_t wx = x - x0, wy = y - y0;
        const int64_t c0 = static_cast<int64_t>(x0), r0 = static_cast<int64_t>(y0);
        const int64_t c1 = (c0 + 1) % w;
        const scalar_t* a = img + 3 * (r0 * w + c0);
        const scalar_t* b = img + 3 * (r0 * w + c1);
        const scalar_t* c = img + 3 * ((r0 + 1) * w + c0);
        const scalar_t* e = img + 3 * ((r0 + 1) * w + c1);
        for (int ch = 0; ch < 3; ++ch) {
          const scalar_t top = a[ch] * (1 - wx) + b[ch] * wx;
          const scalar_t bottom = c[ch] * (1 - wx) + e[ch] * wx;
          op[3 * i + ch] = top * (1 - wy) + bottom * wy;
        }
      }
    });
  });
  return out;
}

// EnvironmentDirectionSampler.pdf: the density (H, W) per steradian of the cell holding
// each direction (N, 3): column floor(u W), row round(v (H - 1)) (half to even, as
// torch.round), both clamped; computed in the directions' dtype.
at::Tensor pdf(const at::Tensor& density, const at::Tensor& d) {
  check_dirs(d, "envmap pdf");
  TORCH_CHECK(density.device().is_cpu() && density.is_contiguous() && density.dim() == 2,
              "envmap pdf: the density must be a contiguous CPU tensor (H, W)");
  const int64_t h = density.size(0), w = density.size(1), n = d.size(0);
  const at::Tensor table = density.to(d.scalar_type());
  at::Tensor out = at::empty({n}, d.options());
  AT_DISPATCH_FLOATING_TYPES(d.scalar_type(), "envmap_pdf", [&] {
    const scalar_t* tp = table.data_ptr<scalar_t>();
    const scalar_t* dp = d.data_ptr<scalar_t>();
    scalar_t* op = out.data_ptr<scalar_t>();
    const scalar_t fw = static_cast<scalar_t>(w), rows = static_cast<scalar_t>(h - 1);
    at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) {
        scalar_t u, v;
        to_uv(dp + 3 * i, u, v);
        const int64_t col = std::min<int64_t>(w - 1, std::max<int64_t>(
            0, static_cast<int64_t>(u * fw)));
        const int64_t row = std::min<int64_t>(h - 1, std::max<int64_t>(
            0, static_cast<int64_t>(std::nearbyint(v * rows))));
        op[i] = tp[row * w + col];
      }
    });
  });
  return out;
}

// EnvironmentDirectionSampler.sample: per row of xi (N, 3) in [0, 1), float64, the cell
// whose cumulative probability cdf (H W) first exceeds xi_0 (torch.searchsorted with
// right=True, the last cell past the end), then the direction uniform in the cell's solid
// angle: cos = cos_top + xi_1 (cos_bottom - cos_top), azimuth 2 pi (col + xi_2) / W.
// Float32 out.
at::Tensor sample(const at::Tensor& cdf, const at::Tensor& cos_top,
                  const at::Tensor& cos_bottom, int64_t width, const at::Tensor& xi) {
  TORCH_CHECK(xi.device().is_cpu() && xi.is_contiguous() && xi.dim() == 2 && xi.size(1) == 3 &&
                  xi.scalar_type() == at::kDouble,
              "envmap sample: xi must be a contiguous CPU float64 tensor (N, 3)");
  for (const at::Tensor* t : {&cdf, &cos_top, &cos_bottom}) {
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous() && t->dim() == 1 &&
                    t->scalar_type() == at::kDouble,
                "envmap sample: the tables must be contiguous CPU float64 vectors");
  }
  const int64_t cells = cdf.size(0), n = xi.size(0);
  TORCH_CHECK(cells == cos_top.size(0) * width && cos_top.size(0) == cos_bottom.size(0),
              "envmap sample: the cdf must have rows x width entries");
  at::Tensor out = at::empty({n, 3}, xi.options().dtype(at::kFloat));
  const double* cp = cdf.data_ptr<double>();
  const double* top = cos_top.data_ptr<double>();
  const double* bottom = cos_bottom.data_ptr<double>();
  const double* xp = xi.data_ptr<double>();
  float* op = out.data_ptr<float>();
  // A guide table: guide[k] is the first cell whose cdf exceeds k / cells, so the search
  // for xi_0 starts there and steps forward a cell or two on average (the same cell as a
  // binary search, in constant expected time).
  std::vector<int64_t> guide(cells);
  for (int64_t k = 0, cell = 0; k < cells; ++k) {
    const double at = static_cast<double>(k) / static_cast<double>(cells);
    while (cell < cells && cp[cell] <= at) ++cell;
    guide[k] = cell;
  }
  at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      const double* r = xp + 3 * i;
      const int64_t k = std::min<int64_t>(
          cells - 1, static_cast<int64_t>(r[0] * static_cast<double>(cells)));
      int64_t cell = guide[k];
      while (cell > 0 && cp[cell - 1] > r[0]) --cell;  // k rounded up: step back
      while (cell < cells && cp[cell] <= r[0]) ++cell;
      cell = std::min(cell, cells - 1);
      const int64_t row = cell / width, col = cell % width;
      const double cos = std::min(1.0, std::max(top[row] + r[1] * (bottom[row] - top[row]),
                                                -1.0));
      const double sin = std::sqrt(std::max(1.0 - cos * cos, 0.0));
      const double phi = (static_cast<double>(col) + r[2]) * (2.0 * kPi / static_cast<double>(width));
      op[3 * i] = static_cast<float>(sin * std::sin(phi));
      op[3 * i + 1] = static_cast<float>(cos);
      op[3 * i + 2] = static_cast<float>(-sin * std::cos(phi));
    }
  });
  return out;
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("lookup", &lookup, "EnvironmentMap.lookup: bilinear radiance at look directions");
  m.def("pdf", &pdf, "EnvironmentDirectionSampler.pdf: density per steradian");
  m.def("sample", &sample, "EnvironmentDirectionSampler.sample: look directions from xi");
}
