// See kernel.h. The cost of a tile is bounded by its pixels, not by its list length or by
// the size of its Gaussians: each pixel stops on its own at transmittance 1e-4 (a tile
// when all its pixels have), a Gaussian is listed only in the tiles its alpha > 1/255
// ellipse reaches (closed-form column range per tile row), and evaluated only on the
// ellipse's column span of each pixel row. The pixel loops run on vectors of pixels of a
// tile row (GCC / Clang vector extensions), without branches: 4 lanes on any CPU (SSE2 on
// x86-64, NEON on ARM) and, with GCC on x86-64, 8 lanes for CPUs with AVX2, picked at run
// time. Both builds do the same float operations per pixel (no FMA contraction), so they
// give the same images; gradients differ only in the order of the lanes' sums.
#include "kernel.h"

#include <cstdlib>
#include <cstring>

#include "kernel_common.h"

#if defined(__GNUC__) && !defined(__clang__)
// The vectors never cross a call boundary between differently compiled code.
#pragma GCC diagnostic ignored "-Wpsabi"
#endif

#define RS_LANES 4
#define RS_ISA baseline
#include "composite_impl.h"
#undef RS_LANES
#undef RS_ISA

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
#define RS_HAVE_AVX2 1
#pragma GCC push_options
#pragma GCC target("avx2")
#define RS_LANES 8
#define RS_ISA avx2
#include "composite_impl.h"
#undef RS_LANES
#undef RS_ISA
#pragma GCC pop_options
#endif

namespace rs {

using detail::make_splat;
using detail::parallel_for;
using detail::row_range;

bool use_avx2() {
#ifdef RS_HAVE_AVX2
  // RAINYSCAPE_RASTERIZER_SIMD=baseline forces the 4-lane build (tests compare the two).
  const char* choice = std::getenv("RAINYSCAPE_RASTERIZER_SIMD");
  if (choice && std::strcmp(choice, "baseline") == 0) return false;
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx2");
#else
  return false;
#endif
}

const char* simd_name() { return use_avx2() ? "avx2 (8 lanes)" : "baseline (4 lanes)"; }

void bin_splats(const Splats& s, const int64_t* order, int threads, Binning& b) {
  const int64_t m = s.cameras * s.gaussians;
  if (m >= (int64_t{1} << 31)) throw std::invalid_argument("more than 2^31 camera-Gaussian rows");
  b.tiles_x = (s.width + kTile - 1) / kTile;
  b.tiles_y = (s.height + kTile - 1) / kTile;
  b.cameras = s.cameras;
  b.gaussians = s.gaussians;
  b.width = s.width;
  b.height = s.height;
  b.splats.resize(static_cast<size_t>(m));
  const int64_t per_cam = static_cast<int64_t>(b.tiles_x) * b.tiles_y;
  const int64_t tiles = s.cameras * per_cam;

  // Calls emit(tile, row) for the tiles of entry i of the sequence (Gaussian order[i] of
  // camera i / N: depth order per camera). `first`: fill the Gaussian's Splat.
  auto visit = [&](int64_t i, bool first, auto&& emit) {
    const int64_t cam = i / s.gaussians;
    const int64_t row = cam * s.gaussians + order[i];
    const int32_t rx = s.radii[2 * row], ry = s.radii[2 * row + 1];
    if (rx <= 0 || ry <= 0) return;
    if (first) b.splats[row] = make_splat(s, row);
    const Splat& p = b.splats[row];
    // The bounding box's tile range, as rasterize_torch.bin_gaussians computes it.
    auto range = [](float mean, int32_t rad, int tiles_n, int& lo, int& hi) {
      const float ts = static_cast<float>(kTile);
      const float l = std::floor((mean - static_cast<float>(rad)) / ts);
      const float h = std::ceil((mean + static_cast<float>(rad)) / ts);
      lo = static_cast<int>(std::min(std::max(l, 0.0f), static_cast<float>(tiles_n)));
      hi = static_cast<int>(std::min(std::max(h, 0.0f), static_cast<float>(tiles_n)));
    };
    int tx0, tx1, ty0, ty1;
    range(p.mx, rx, b.tiles_x, tx0, tx1);
    range(p.my, ry, b.tiles_y, ty0, ty1);
    for (int ty = ty0; ty < ty1; ++ty) {
      int lo = tx0, hi = tx1 - 1;
      if (p.bounded) {
        // Columns the ellipse reaches on the tile's pixel rows: the extremes of its left
        // edge (convex in y) and right edge (concave) over the rows, at the ellipse's
        // leftmost / rightmost points clamped into them.
        int r0, r1;
        if (!row_range(p, ty * kTile, std::min(kTile, s.height - ty * kTile), r0, r1)) continue;
        const double y_lo = ty * kTile + r0 + 0.5, y_hi = ty * kTile + r1 + 0.5;
        const double turn = p.slope / (p.k2 + p.slope * p.slope) *
                            std::sqrt(p.k1 * (1.0 + p.slope * p.slope / p.k2));
        auto edge = [&](double y, double side) {
          const double dy = p.my - y;
          return p.mx + p.slope * dy + side * std::sqrt(std::max(0.0, p.k1 - p.k2 * dy * dy));
        };
        const double x_min = edge(std::min(std::max(p.my + turn, y_lo), y_hi), -1.0);
        const double x_max = edge(std::min(std::max(p.my - turn, y_lo), y_hi), 1.0);
        const double col_lo = std::ceil(x_min - 0.5 - 1e-6), col_hi = std::floor(x_max - 0.5 + 1e-6);
        if (!(col_lo <= col_hi) || col_hi < 0 || col_lo >= s.width) continue;
        lo = std::max(lo, static_cast<int>(std::max(col_lo, 0.0)) / kTile);
        hi = std::min(hi, static_cast<int>(std::min(col_hi, s.width - 1.0)) / kTile);
      }
      for (int tx = lo; tx <= hi; ++tx) emit(cam * per_cam + static_cast<int64_t>(ty) * b.tiles_x + tx, row);
    }
  };
  // Each chunk of the sequence counts, then fills, its own slice of every tile's list, so
  // the lists come out depth-sorted without sorting the pairs.
  const int64_t chunks = std::max<int64_t>(1, std::min<int64_t>(4 * int64_t{threads}, m / 2048 + 1));
  const int64_t chunk_len = (m + chunks - 1) / chunks;
  std::vector<int64_t> cursor(static_cast<size_t>(chunks * tiles), 0);
  parallel_for(chunks, threads, [&](int64_t ch, int) {
    int64_t* count = cursor.data() + ch * tiles;
    const int64_t end = std::min(m, (ch + 1) * chunk_len);
    for (int64_t i = ch * chunk_len; i < end; ++i)
      visit(i, true, [&](int64_t tile, int64_t) { ++count[tile]; });
  });
  b.tile_start.assign(static_cast<size_t>(tiles + 1), 0);
  int64_t total = 0;
  for (int64_t t = 0; t < tiles; ++t) {
    b.tile_start[t] = total;
    for (int64_t ch = 0; ch < chunks; ++ch) {
      const int64_t n = cursor[ch * tiles + t];
      cursor[ch * tiles + t] = total;
      total += n;
    }
  }
  b.tile_start[tiles] = total;
  b.ids.assign(static_cast<size_t>(total), 0);
  parallel_for(chunks, threads, [&](int64_t ch, int) {
    int64_t* at = cursor.data() + ch * tiles;
    const int64_t end = std::min(m, (ch + 1) * chunk_len);
    for (int64_t i = ch * chunk_len; i < end; ++i)
      visit(i, false, [&](int64_t tile, int64_t row) { b.ids[at[tile]++] = static_cast<int32_t>(row); });
  });
}
void composite_forward(const float* features, int channels, Binning& b, float* out,
                       int threads) {
#ifdef RS_HAVE_AVX2
  if (use_avx2()) return avx2::composite_forward(features, channels, b, out, threads);
#endif
  baseline::composite_forward(features, channels, b, out, threads);
}

void composite_backward(const float* opacities, const float* features, int channels,
                        const Binning& b, const float* grad_out, float* grad_means2d,
                        float* grad_conics, float* grad_opacities, float* grad_features,
                        int threads) {
#ifdef RS_HAVE_AVX2
  if (use_avx2())
    return avx2::composite_backward(opacities, features, channels, b, grad_out, grad_means2d,
                                    grad_conics, grad_opacities, grad_features, threads);
#endif
  baseline::composite_backward(opacities, features, channels, b, grad_out, grad_means2d,
                               grad_conics, grad_opacities, grad_features, threads);
}

}  // namespace rs
