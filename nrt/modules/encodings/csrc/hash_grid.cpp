// Fused CPU kernels of HashGrid (nrt/modules/encodings/hash_grid.py): the encoding and its
// gradient with respect to the table, in one pass each instead of the PyTorch path's
// per-level chain of tensors. Built at first use by nrt/modules/encodings/fused_hash_grid.py.
//
// The arithmetic is the PyTorch path's, operation by operation, in the points' dtype: clamp
// x to [0, 1]; per level pos = x * N, base = min(floor(pos), N - 1), frac = pos - base;
// corner c = (i, j, k) = (c & 1, c >> 1 & 1, c >> 2 & 1); weight ((wx * wy) * wz) with
// w = frac or 1 - frac; row = dense or hashed index + the level's offset; feature
// = sum over the 8 corners in order of weight * table row. Only the order of that sum (and
// of the backward's sums) may differ from PyTorch's reductions.
#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/csrc/utils/pybind.h>

#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr uint64_t kPrimeY = 2654435761ull;  // tiny-cuda-nn's primes (PRIMES in hash_grid.py);
constexpr uint64_t kPrimeZ = 805459861ull;   // x's is 1
constexpr int64_t kPointGrain = 256;         // points per task at least (16 levels x 8 corners)

struct Levels {  // HashGrid's per-level constants
  std::vector<int64_t> resolution, offset;
  std::vector<bool> dense;
  uint64_t mask;  // table_size - 1 (a power of two)
};

template <typename scalar_t>
struct Cell {  // one point's cell on one level: its 8 corners' table rows and weights
  int64_t row[8];
  scalar_t weight[8];
};

template <typename scalar_t>
inline void locate(const scalar_t* point, const Levels& lv, int64_t level,
                   Cell<scalar_t>& cell) {
  const int64_t res = lv.resolution[level];
  const scalar_t n = static_cast<scalar_t>(res), last = static_cast<scalar_t>(res - 1);
  int64_t base[3];
  scalar_t w[3][2];  // [axis][corner bit]: 1 - frac, frac
  for (int a = 0; a < 3; ++a) {
    scalar_t x = point[a];
    TORCH_CHECK(!std::isnan(x), "HashGrid: a point has a NaN coordinate");
    x = x < scalar_t(0) ? scalar_t(0) : (x > scalar_t(1) ? scalar_t(1) : x);
    const scalar_t pos = x * n;
    scalar_t b = std::floor(pos);
    b = b > last ? last : b;
    const scalar_t frac = pos - b;
    base[a] = static_cast<int64_t>(b);
    w[a][0] = scalar_t(1) - frac;
    w[a][1] = frac;
  }
  const bool dense = lv.dense[level];
  const int64_t side = res + 1;
  for (int c = 0; c < 8; ++c) {
    const int i = c & 1, j = (c >> 1) & 1, k = (c >> 2) & 1;
    const int64_t vx = base[0] + i, vy = base[1] + j, vz = base[2] + k;
    int64_t idx;
    if (dense) {
      idx = vx + side * (vy + side * vz);
    } else {
      idx = static_cast<int64_t>((static_cast<uint64_t>(vx) ^ static_cast<uint64_t>(vy) * kPrimeY ^
                                  static_cast<uint64_t>(vz) * kPrimeZ) & lv.mask);
    }
    cell.row[c] = idx + lv.offset[level];
    cell.weight[c] = w[0][i] * w[1][j] * w[2][k];
  }
}

Levels levels_of(const std::vector<int64_t>& resolution, const std::vector<int64_t>& offset,
                 const std::vector<bool>& dense, int64_t table_size) {
  TORCH_CHECK(resolution.size() == offset.size() && resolution.size() == dense.size(),
              "HashGrid: one resolution, offset and dense flag per level");
  TORCH_CHECK(table_size > 0 && (table_size & (table_size - 1)) == 0,
              "HashGrid: the table size must be a power of two");
  return Levels{resolution, offset, dense, static_cast<uint64_t>(table_size - 1)};
}

void check(const at::Tensor& t, const at::Tensor& like, int64_t columns, const char* what) {
  TORCH_CHECK(t.device().is_cpu() && t.is_contiguous() && t.dim() == 2 && t.size(1) == columns,
              "HashGrid fused: ", what, " must be a contiguous CPU tensor (n, ", columns, ")");
  TORCH_CHECK(t.scalar_type() == like.scalar_type(), "HashGrid fused: ", what,
              " must have the table's dtype");
}

// (P, 3) points, (R, F) table -> (P, levels * F) features. Parallel over points: each task
// writes its own output rows, so any thread count gives the same bits.
at::Tensor forward(const at::Tensor& x, const at::Tensor& table,
                   const std::vector<int64_t>& resolution, const std::vector<int64_t>& offset,
                   const std::vector<bool>& dense, int64_t table_size) {
  const Levels lv = levels_of(resolution, offset, dense, table_size);
  check(table, table, table.size(1), "the table");
  check(x, table, 3, "the points");
  const int64_t points = x.size(0), features = table.size(1);
  const int64_t levels = static_cast<int64_t>(resolution.size());
  at::Tensor out = at::empty({points, levels * features}, table.options());
  AT_DISPATCH_FLOATING_TYPES(table.scalar_type(), "hash_grid_forward", [&] {
    const scalar_t* xp = x.data_ptr<scalar_t>();
    const scalar_t* tp = table.data_ptr<scalar_t>();
    scalar_t* op = out.data_ptr<scalar_t>();
    at::parallel_for(0, points, kPointGrain, [&](int64_t begin, int64_t end) {
      Cell<scalar_t> cell;
      for (int64_t p = begin; p < end; ++p) {
        scalar_t* o = op + p * levels * features;
        for (int64_t level = 0; level < levels; ++level) {
          locate(xp + 3 * p, lv, level, cell);
          for (int64_t f = 0; f < features; ++f) {
            scalar_t acc = cell.weight[0] * tp[cell.row[0] * features + f];
            for (int c = 1; c < 8; ++c) acc += cell.weight[c] * tp[cell.row[c] * features + f];
            o[level * features + f] = acc;
          }
        }
      }
    });
  });
  return out;
}

// d loss / d table (rows, F) from d loss / d features (P, levels * F): the scatter-add of
// grad * weight into each corner's row. Levels own disjoint slices of the table, so a
// level is one task, run by one thread over the points in order: no two threads write the
// same row (no atomics, no per-thread copies of the table), and each row's sum has the same
// order for any thread count, so the gradient is bit-for-bit reproducible. Atomic adds
// would scale past the level count but sum in a scheduling-dependent order (and a
// compare-and-swap loop per float add); per-thread tables would cost threads x table
// memory and a reduction. Levels go to threads round-robin, so that each thread gets
// coarse (cache-resident) and fine (hashed) levels alike.
at::Tensor backward(const at::Tensor& grad, const at::Tensor& x, int64_t rows,
                    const std::vector<int64_t>& resolution, const std::vector<int64_t>& offset,
                    const std::vector<bool>& dense, int64_t table_size) {
  const Levels lv = levels_of(resolution, offset, dense, table_size);
  const int64_t levels = static_cast<int64_t>(resolution.size());
  TORCH_CHECK(levels > 0 && grad.dim() == 2 && grad.size(1) % levels == 0,
              "HashGrid fused: the gradient must be (P, levels * features)");
  const int64_t points = x.size(0), features = grad.size(1) / levels;
  check(x, grad, 3, "the points");
  check(grad, grad, levels * features, "the gradient");
  TORCH_CHECK(grad.size(0) == points, "HashGrid fused: one gradient row per point");
  at::Tensor gt = at::zeros({rows, features}, grad.options());
  const int64_t workers = std::min<int64_t>(at::get_num_threads(), levels);
  AT_DISPATCH_FLOATING_TYPES(grad.scalar_type(), "hash_grid_backward", [&] {
    const scalar_t* xp = x.data_ptr<scalar_t>();
    const scalar_t* gp = grad.data_ptr<scalar_t>();
    scalar_t* tp = gt.data_ptr<scalar_t>();
    at::parallel_for(0, workers, 1, [&](int64_t begin, int64_t end) {
      Cell<scalar_t> cell;
      for (int64_t worker = begin; worker < end; ++worker) {
        for (int64_t level = worker; level < levels; level += workers) {
          for (int64_t p = 0; p < points; ++p) {
            locate(xp + 3 * p, lv, level, cell);
            const scalar_t* g = gp + (p * levels + level) * features;
            for (int c = 0; c < 8; ++c) {
              scalar_t* row = tp + cell.row[c] * features;
              for (int64_t f = 0; f < features; ++f) row[f] += g[f] * cell.weight[c];
            }
          }
        }
      }
    });
  });
  return gt;
}

// How many threads a parallel_for over many items runs on (a build without OpenMP: 1).
int64_t parallel_threads() {
  std::vector<char> seen(at::get_num_threads(), 0);
  at::parallel_for(0, 1 << 16, 1, [&](int64_t, int64_t) { seen[at::get_thread_num()] = 1; });
  int64_t n = 0;
  for (char s : seen) n += s;
  return n;
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &forward, "HashGrid's encoding of points (P, 3)");
  m.def("backward", &backward, "HashGrid's table gradient");
  m.def("parallel_threads", &parallel_threads, "threads a parallel_for runs on");
}
