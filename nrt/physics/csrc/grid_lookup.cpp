// Fused CPU kernels of sample_grid (nrt/physics/volume.py): the trilinear, cell-centred,
// edge-clamped lookup of a channels-last grid (Nz, Ny, Nx, C) at world points, and its
// gradient with respect to the grid, in one pass each instead of the PyTorch path's
// normalise / permute / grid_sample / transpose chain; and optical_depth's march (every
// stratum of a ray looked up and averaged, the points and their values never stored), with
// its gradient. Built at first use by nrt/physics/fused_lookup.py.
//
// The forward's arithmetic is the PyTorch path's, operation by operation, in the points'
// dtype: u = (p - lo) / (hi - lo) * 2 - 1 per axis; grid_sample's source index with
// align_corners=false, i = ((u + 1) * n - 1) / 2, clipped to [0, n - 1] (its border
// padding, with its min / max order); base b = floor(i); weights (b + 1 - i) and (i - b) per
// axis, multiplied x * y * z; the 8 corners summed in grid_sample's order (x fastest, then y,
// then z), corners outside the grid left out. So its values are grid_sample's bit for bit.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr int64_t kPointGrain = 512;        // points per forward task at least
constexpr int64_t kPointsPerPart = 16384;   // backward: points per partial gradient at least
constexpr int64_t kMostParts = 8;           // backward: partial gradients at most
constexpr int64_t kMostPartValues = 1 << 24;  // backward: values of all partials at most

template <typename scalar_t>
struct Box {  // the box's low corner and extent per axis, in the points' dtype
  scalar_t lo[3], extent[3];
  explicit Box(const at::Tensor& bbox) {
    const scalar_t* b = bbox.data_ptr<scalar_t>();
    for (int a = 0; a < 3; ++a) {
      lo[a] = b[a];
      extent[a] = b[3 + a] - b[a];
    }
  }
};

template <typename scalar_t>
struct Corners {  // one point's 8 corners: flat cell index (-1: outside) and weight
  int64_t cell[8];
  scalar_t weight[8];
};

template <typename scalar_t>
inline void locate(const scalar_t* p, const Box<scalar_t>& box, const int64_t* size,
                   Corners<scalar_t>& out) {
  int64_t base[3];
  scalar_t w[3][2];  // [axis][corner bit]: b + 1 - i, i - b
  for (int a = 0; a < 3; ++a) {
    const scalar_t u = (p[a] - box.lo[a]) / box.extent[a] * scalar_t(2) - scalar_t(1);
    const scalar_t n = static_cast<scalar_t>(size[a]);
    scalar_t i = ((u + scalar_t(1)) * n - scalar_t(1)) / scalar_t(2);
    i = std::min(static_cast<scalar_t>(size[a] - 1), std::max(i, scalar_t(0)));
    base[a] = static_cast<int64_t>(std::floor(i));
    w[a][0] = static_cast<scalar_t>(base[a] + 1) - i;
    w[a][1] = i - static_cast<scalar_t>(base[a]);
  }
  for (int c = 0; c < 8; ++c) {
    const int bx = c & 1, by = (c >> 1) & 1, bz = (c >> 2) & 1;
    const int64_t x = base[0] + bx, y = base[1] + by, z = base[2] + bz;
    const bool inside = x >= 0 && x < size[0] && y >= 0 && y < size[1] && z >= 0 &&
                        z < size[2];
    out.cell[c] = inside ? x + size[0] * (y + size[1] * z) : -1;
    out.weight[c] = w[0][bx] * w[1][by] * w[2][bz];
  }
}

// out[ch] += the corners' values times their weights, the corners in grid_sample's order.
template <typename scalar_t>
inline void gather(const Corners<scalar_t>& k, const scalar_t* grid, int64_t c, scalar_t* out) {
  for (int corner = 0; corner < 8; ++corner) {
    if (k.cell[corner] < 0) continue;
    const scalar_t* v = grid + k.cell[corner] * c;
    for (int64_t ch = 0; ch < c; ++ch) out[ch] += v[ch] * k.weight[corner];
  }
}

// Each corner's row of dst += g times its weight (the lookup's backward for one point).
template <typename scalar_t>
inline void scatter(const Corners<scalar_t>& k, const scalar_t* g, int64_t c, scalar_t* dst) {
  for (int corner = 0; corner < 8; ++corner) {
    if (k.cell[corner] < 0) continue;
    scalar_t* row = dst + k.cell[corner] * c;
    for (int64_t ch = 0; ch < c; ++ch) row[ch] += g[ch] * k.weight[corner];
  }
}

// The sum of the partial gradients (parts, ...), in order.
at::Tensor sum_parts(const at::Tensor& partial, int64_t parts) {
  if (parts == 1) return partial[0];
  at::Tensor total = partial[0].clone();
  for (int64_t part = 1; part < parts; ++part) total.add_(partial[part]);
  return total;
}

struct Shape {  // the grid's cells per axis, x first, and its channels
  int64_t size[3];
  int64_t channels;
};

Shape check(const at::Tensor& grid, const at::Tensor& points, const at::Tensor& bbox) {
  TORCH_CHECK(grid.device().is_cpu() && grid.is_contiguous() && grid.dim() == 4,
              "sample_grid fused: the grid must be a contiguous CPU tensor (Nz, Ny, Nx, C)");
  TORCH_CHECK(points.device().is_cpu() && points.is_contiguous() && points.dim() == 2 &&
                  points.size(1) == 3,
              "sample_grid fused: the points must be a contiguous CPU tensor (P, 3)");
  TORCH_CHECK(bbox.device().is_cpu() && bbox.is_contiguous() && bbox.dim() == 2 &&
                  bbox.size(0) == 2 && bbox.size(1) == 3,
              "sample_grid fused: the box must be a contiguous CPU tensor (2, 3)");
  TORCH_CHECK(grid.scalar_type() == points.scalar_type() &&
                  bbox.scalar_type() == points.scalar_type(),
              "sample_grid fused: grid, points and box must have one dtype");
  return Shape{{grid.size(2), grid.size(1), grid.size(0)}, grid.size(3)};
}

// (Nz, Ny, Nx, C) grid, (P, 3) points, (2, 3) box -> (P, C). Parallel over points: each
// task writes its own output rows, so any thread count gives the same bits.
at::Tensor forward(const at::Tensor& grid, const at::Tensor& points, const at::Tensor& bbox) {
  const Shape s = check(grid, points, bbox);
  const int64_t n = points.size(0), c = s.channels;
  at::Tensor out = at::empty({n, c}, grid.options());
  AT_DISPATCH_FLOATING_TYPES(grid.scalar_type(), "grid_lookup_forward", [&] {
    const scalar_t* g = grid.data_ptr<scalar_t>();
    const scalar_t* pp = points.data_ptr<scalar_t>();
    const Box<scalar_t> box(bbox);
    scalar_t* op = out.data_ptr<scalar_t>();
    at::parallel_for(0, n, kPointGrain, [&](int64_t begin, int64_t end) {
      Corners<scalar_t> k;
      for (int64_t p = begin; p < end; ++p) {
        locate(pp + 3 * p, box, s.size, k);
        scalar_t* o = op + p * c;
        for (int64_t ch = 0; ch < c; ++ch) o[ch] = scalar_t(0);
        gather(k, g, c, o);
      }
    });
  });
  return out;
}

// How many partial gradients the backward sums: from the sizes alone (never the thread
// count), so that the gradient has the same bits on any number of threads.
int64_t parts_for(int64_t points, int64_t values) {
  int64_t parts = std::min(kMostParts, std::max<int64_t>(1, points / kPointsPerPart));
  while (parts > 1 && parts * values > kMostPartValues) --parts;
  return parts;
}

// d loss / d grid (Nz, Ny, Nx, C) from d loss / d values (P, C): the scatter-add of
// grad * weight into each corner. The points are cut into a fixed number of contiguous
// parts (parts_for), each scattered in order into a partial gradient of its own by one task,
// and the partials are summed in order: no atomics, and the sums' order depends on the sizes
// only.
at::Tensor backward(const at::Tensor& grad, const at::Tensor& points, const at::Tensor& bbox,
                    at::IntArrayRef grid_shape) {
  TORCH_CHECK(grid_shape.size() == 4, "sample_grid fused: the grid's shape is (Nz, Ny, Nx, C)");
  const int64_t cells = grid_shape[0] * grid_shape[1] * grid_shape[2], c = grid_shape[3];
  const at::Tensor like = at::empty({0, 0, 0, c}, grad.options());
  const Shape s{{grid_shape[2], grid_shape[1], grid_shape[0]}, c};
  check(like, points, bbox);
  TORCH_CHECK(grad.device().is_cpu() && grad.is_contiguous() && grad.dim() == 2 &&
                  grad.size(0) == points.size(0) && grad.size(1) == c,
              "sample_grid fused: the gradient must be a contiguous CPU tensor (P, C)");
  const int64_t n = points.size(0), parts = parts_for(n, cells * c);
  at::Tensor partial = at::zeros({parts, grid_shape[0], grid_shape[1], grid_shape[2], c},
                                 grad.options());
  AT_DISPATCH_FLOATING_TYPES(grad.scalar_type(), "grid_lookup_backward", [&] {
    const scalar_t* gp = grad.data_ptr<scalar_t>();
    const scalar_t* pp = points.data_ptr<scalar_t>();
    const Box<scalar_t> box(bbox);
    scalar_t* out = partial.data_ptr<scalar_t>();
    at::parallel_for(0, parts, 1, [&](int64_t begin, int64_t end) {
      Corners<scalar_t> k;
      for (int64_t part = begin; part < end; ++part) {
        scalar_t* dst = out + part * cells * c;
        const int64_t first = n * part / parts, last = n * (part + 1) / parts;
        for (int64_t p = first; p < last; ++p) {
          locate(pp + 3 * p, box, s.size, k);
          scatter(k, gp + p * c, c, dst);
        }
      }
    });
  });
  return sum_parts(partial, parts);
}

// optical_depth (nrt/physics/volume.py) through a grid: for each ray (o, d, t0, length,
// offset) the mean over s < S of the lookup at o + (t0 + length (s + offset) / S) d, times
// length. The points are formed with the PyTorch path's arithmetic (frac, t, then o + t d
// per axis), so each lookup is grid_sample's; the strata are summed in order.
template <typename scalar_t>
struct Rays {
  const scalar_t *o, *d, *t0, *length, *offset;
  int64_t strata;
  inline void point(int64_t r, int64_t s, scalar_t* p) const {
    const scalar_t frac = (static_cast<scalar_t>(s) + offset[r]) / static_cast<scalar_t>(strata);
    const scalar_t t = t0[r] + length[r] * frac;
    for (int a = 0; a < 3; ++a) p[a] = o[3 * r + a] + t * d[3 * r + a];
  }
};

int64_t check_rays(const at::Tensor& origins, const at::Tensor& dirs, const at::Tensor& t0,
                   const at::Tensor& length, const at::Tensor& offset, int64_t strata) {
  const int64_t n = origins.size(0);
  TORCH_CHECK(dirs.device().is_cpu() && dirs.is_contiguous() && dirs.sizes() == origins.sizes() &&
                  dirs.scalar_type() == origins.scalar_type(),
              "optical_depth fused: the directions must be a contiguous CPU tensor like the "
              "origins (N, 3)");
  for (const at::Tensor* t : {&t0, &length, &offset}) {
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous() && t->dim() == 1 &&
                    t->size(0) == n && t->scalar_type() == origins.scalar_type(),
                "optical_depth fused: t0, length and offset must be contiguous CPU tensors "
                "(N,) of the origins' dtype");
  }
  TORCH_CHECK(strata > 0, "optical_depth fused: at least one stratum per ray");
  return n;
}

template <typename scalar_t>
Rays<scalar_t> rays_of(const at::Tensor& origins, const at::Tensor& dirs, const at::Tensor& t0,
                       const at::Tensor& length, const at::Tensor& offset, int64_t strata) {
  return Rays<scalar_t>{origins.data_ptr<scalar_t>(), dirs.data_ptr<scalar_t>(),
                        t0.data_ptr<scalar_t>(), length.data_ptr<scalar_t>(),
                        offset.data_ptr<scalar_t>(), strata};
}

// (Nz, Ny, Nx, C) grid, (N, 3) origins and directions, (N,) t0, length and offset, (2, 3)
// box -> (N, C). Parallel over rays: each task writes its own rows.
at::Tensor march_forward(const at::Tensor& grid, const at::Tensor& origins,
                         const at::Tensor& dirs, const at::Tensor& t0, const at::Tensor& length,
                         const at::Tensor& offset, const at::Tensor& bbox, int64_t strata) {
  const Shape s = check(grid, origins, bbox);
  const int64_t n = check_rays(origins, dirs, t0, length, offset, strata), c = s.channels;
  at::Tensor out = at::empty({n, c}, grid.options());
  AT_DISPATCH_FLOATING_TYPES(grid.scalar_type(), "grid_march_forward", [&] {
    const scalar_t* g = grid.data_ptr<scalar_t>();
    const Rays<scalar_t> rays = rays_of<scalar_t>(origins, dirs, t0, length, offset, strata);
    const Box<scalar_t> box(bbox);
    scalar_t* op = out.data_ptr<scalar_t>();
    const int64_t grain = std::max<int64_t>(1, kPointGrain / strata);
    at::parallel_for(0, n, grain, [&](int64_t begin, int64_t end) {
      Corners<scalar_t> k;
      scalar_t p[3];
      std::vector<scalar_t> sum(c), value(c);
      for (int64_t r = begin; r < end; ++r) {
        std::fill(sum.begin(), sum.end(), scalar_t(0));
        for (int64_t st = 0; st < strata; ++st) {
          rays.point(r, st, p);
          locate(p, box, s.size, k);
          std::fill(value.begin(), value.end(), scalar_t(0));
          gather(k, g, c, value.data());
          for (int64_t ch = 0; ch < c; ++ch) sum[ch] += value[ch];
        }
        scalar_t* o = op + r * c;
        for (int64_t ch = 0; ch < c; ++ch)
          o[ch] = sum[ch] / static_cast<scalar_t>(strata) * rays.length[r];
      }
    });
  });
  return out;
}

// d loss / d grid from d loss / d depth (N, C): each stratum's lookup receives
// grad * length / S, scattered as the lookup's backward does (a fixed number of parts by the
// sizes alone, each summed in order, then the partials in order).
at::Tensor march_backward(const at::Tensor& grad, const at::Tensor& origins,
                          const at::Tensor& dirs, const at::Tensor& t0, const at::Tensor& length,
                          const at::Tensor& offset, const at::Tensor& bbox, int64_t strata,
                          at::IntArrayRef grid_shape) {
  TORCH_CHECK(grid_shape.size() == 4, "optical_depth fused: the grid's shape is (Nz, Ny, Nx, C)");
  const int64_t cells = grid_shape[0] * grid_shape[1] * grid_shape[2], c = grid_shape[3];
  const Shape s{{grid_shape[2], grid_shape[1], grid_shape[0]}, c};
  check(at::empty({0, 0, 0, c}, grad.options()), origins, bbox);
  const int64_t n = check_rays(origins, dirs, t0, length, offset, strata);
  TORCH_CHECK(grad.device().is_cpu() && grad.is_contiguous() && grad.dim() == 2 &&
                  grad.size(0) == n && grad.size(1) == c,
              "optical_depth fused: the gradient must be a contiguous CPU tensor (N, C)");
  const int64_t parts = parts_for(n * strata, cells * c);
  at::Tensor partial = at::zeros({parts, grid_shape[0], grid_shape[1], grid_shape[2], c},
                                 grad.options());
  AT_DISPATCH_FLOATING_TYPES(grad.scalar_type(), "grid_march_backward", [&] {
    const scalar_t* gp = grad.data_ptr<scalar_t>();
    const Rays<scalar_t> rays = rays_of<scalar_t>(origins, dirs, t0, length, offset, strata);
    const Box<scalar_t> box(bbox);
    scalar_t* out = partial.data_ptr<scalar_t>();
    at::parallel_for(0, parts, 1, [&](int64_t begin, int64_t end) {
      Corners<scalar_t> k;
      scalar_t p[3];
      std::vector<scalar_t> each(c);
      for (int64_t part = begin; part < end; ++part) {
        scalar_t* dst = out + part * cells * c;
        const int64_t first = n * part / parts, last = n * (part + 1) / parts;
        for (int64_t r = first; r < last; ++r) {
          for (int64_t ch = 0; ch < c; ++ch)
            each[ch] = gp[r * c + ch] * rays.length[r] / static_cast<scalar_t>(strata);
          for (int64_t st = 0; st < strata; ++st) {
            rays.point(r, st, p);
            locate(p, box, s.size, k);
            scatter(k, each.data(), c, dst);
          }
        }
      }
    });
  });
  return sum_parts(partial, parts);
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &forward, "sample_grid's lookup of points (P, 3)");
  m.def("backward", &backward, "sample_grid's gradient with respect to the grid");
  m.def("march_forward", &march_forward, "optical_depth's march through a grid");
  m.def("march_backward", &march_backward,
        "optical_depth's march: the gradient with respect to the grid");
}
