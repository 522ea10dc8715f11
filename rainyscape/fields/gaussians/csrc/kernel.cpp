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

namespace {

// Visible rows of camera `cam` (index order), stably sorted by depth: an LSD radix sort on the
// float bits (depths of visible Gaussians are > near > 0, so the bits order as the values).
void depth_order(const Splats& s, const float* depths, int64_t cam, std::vector<int32_t>& out) {
  std::vector<uint32_t> keys, keys_tmp;
  std::vector<int32_t> rows, rows_tmp;
  for (int64_t g = 0; g < s.gaussians; ++g) {
    const int64_t row = cam * s.gaussians + g;
    if (s.radii[2 * row] <= 0 || s.radii[2 * row + 1] <= 0) continue;
    uint32_t key;
    std::memcpy(&key, depths + row, sizeof key);
    keys.push_back(key);
    rows.push_back(static_cast<int32_t>(row));
  }
  keys_tmp.resize(keys.size());
  rows_tmp.resize(rows.size());
  for (int shift = 0; shift < 32; shift += 11) {
    size_t count[2049] = {};
    for (uint32_t key : keys) ++count[((key >> shift) & 2047u) + 1];
    for (int i = 0; i < 2048; ++i) count[i + 1] += count[i];
    for (size_t i = 0; i < keys.size(); ++i) {
      const size_t at = count[(keys[i] >> shift) & 2047u]++;
      keys_tmp[at] = keys[i];
      rows_tmp[at] = rows[i];
    }
    keys.swap(keys_tmp);
    rows.swap(rows_tmp);
  }
  out.insert(out.end(), rows.begin(), rows.end());
}

}  // namespace

void bin_splats(const Splats& s, const float* depths, int threads, Binning& b) {
  const int64_t m = s.cameras * s.gaussians;
  if (m >= (int64_t{1} << 31)) throw std::invalid_argument("more than 2^31 camera-Gaussian rows");
  b.tiles_x = (s.width + kTile - 1) / kTile;
  b.tiles_y = (s.height + kTile - 1) / kTile;
  b.cameras = s.cameras;
  b.gaussians = s.gaussians;
  b.width = s.width;
  b.height = s.height;
  const int64_t per_cam = static_cast<int64_t>(b.tiles_x) * b.tiles_y;
  const int64_t tiles = s.cameras * per_cam;
  b.rows.clear();
  for (int64_t cam = 0; cam < s.cameras; ++cam) depth_order(s, depths, cam, b.rows);
  const int64_t visible = static_cast<int64_t>(b.rows.size());
  b.splats.resize(static_cast<size_t>(visible));
  // Per Gaussian: its bounding box's tile range, as rasterize_torch.bin_gaussians computes
  // it, and where its tile rows' column ranges go.
  struct Box {
    int tx0, tx1, ty0, ty1;
  };
  std::vector<Box> boxes(static_cast<size_t>(visible));
  std::vector<int64_t> row_start(static_cast<size_t>(visible) + 1, 0);
  const int64_t block = 4096;
  parallel_for((visible + block - 1) / block, threads, [&](int64_t blk, int) {
    const int64_t end = std::min(visible, (blk + 1) * block);
    for (int64_t i = blk * block; i < end; ++i) {
#if defined(__GNUC__)
      if (i + 16 < end) {  // the rows are in depth order: scattered reads
        const int64_t ahead = b.rows[i + 16];
        __builtin_prefetch(s.means2d + 2 * ahead);
        __builtin_prefetch(s.conics + 3 * ahead);
        __builtin_prefetch(s.opacities + ahead);
        __builtin_prefetch(s.radii + 2 * ahead);
      }
#endif
      const Splat p = make_splat(s, b.rows[i]);
      b.splats[i] = p;
      auto range = [](float mean, int32_t rad, int tiles_n, int& lo, int& hi) {
        const float ts = static_cast<float>(kTile);
        const float l = std::floor((mean - static_cast<float>(rad)) / ts);
        const float h = std::ceil((mean + static_cast<float>(rad)) / ts);
        lo = static_cast<int>(std::min(std::max(l, 0.0f), static_cast<float>(tiles_n)));
        hi = static_cast<int>(std::min(std::max(h, 0.0f), static_cast<float>(tiles_n)));
      };
      Box& box = boxes[i];
      range(p.mx, p.rx, b.tiles_x, box.tx0, box.tx1);
      range(p.my, p.ry, b.tiles_y, box.ty0, box.ty1);
      row_start[i + 1] = box.ty1 - box.ty0;
    }
  });
  for (int64_t i = 0; i < visible; ++i) row_start[i + 1] += row_start[i];
  // Tile columns [lo, hi] reached on each of a Gaussian's tile rows (lo > hi: none),
  // computed by the counting pass and read by the filling pass.
  std::vector<int32_t> spans(static_cast<size_t>(2 * row_start[visible]));

  // Counts the tiles that the Gaussian of rank i reaches, row by row, into count[].
  auto count_tiles = [&](int64_t i, int64_t* count) {
    const Splat& p = b.splats[i];
    const Box& box = boxes[i];
    int32_t* span = spans.data() + 2 * row_start[i];
    const int64_t cam_tile = b.rows[i] / s.gaussians * per_cam;
    for (int ty = box.ty0; ty < box.ty1; ++ty, span += 2) {
      int lo = box.tx0, hi = box.tx1 - 1;
      if (p.bounded && (box.tx1 - box.tx0 > 1 || box.ty1 - box.ty0 > 1)) {
        // Columns the ellipse reaches on the tile's pixel rows: the extremes of its left
        // edge (convex in y) and right edge (concave) over the rows, at the ellipse's
        // leftmost / rightmost points clamped into them. (A box inside one tile is listed
        // there: no finer test pays off.)
        int r0, r1;
        if (!row_range(p, ty * kTile, std::min(kTile, s.height - ty * kTile), r0, r1)) {
          hi = lo - 1;
        } else {
          const double y_lo = ty * kTile + r0 + 0.5, y_hi = ty * kTile + r1 + 0.5;
          auto edge = [&](double y, double side) {
            const double dy = p.my - y;
            return p.mx + p.slope * dy + side * std::sqrt(std::max(0.0, p.k1 - p.k2 * dy * dy));
          };
          const double x_min = edge(std::min(std::max(p.my + p.turn, y_lo), y_hi), -1.0);
          const double x_max = edge(std::min(std::max(p.my - p.turn, y_lo), y_hi), 1.0);
          const double col_lo = std::ceil(x_min - 0.5 - 1e-6);
          const double col_hi = std::floor(x_max - 0.5 + 1e-6);
          if (!(col_lo <= col_hi) || col_hi < 0 || col_lo >= s.width) {
            hi = lo - 1;
          } else {
            lo = std::max(lo, static_cast<int>(std::max(col_lo, 0.0)) / kTile);
            hi = std::min(hi, static_cast<int>(std::min(col_hi, s.width - 1.0)) / kTile);
          }
        }
      }
      span[0] = lo;
      span[1] = hi;
      const int64_t row_tile = cam_tile + static_cast<int64_t>(ty) * b.tiles_x;
      for (int tx = lo; tx <= hi; ++tx) ++count[row_tile + tx];
    }
  };
  // Each chunk of ranks counts, then fills, its own slice of every tile's list, so the lists
  // come out in rank order (front to back) without sorting the pairs.
  const int64_t chunks = std::max<int64_t>(1, std::min<int64_t>(4 * int64_t{threads}, visible / 2048 + 1));
  const int64_t chunk_len = (visible + chunks - 1) / chunks;
  std::vector<int64_t> cursor(static_cast<size_t>(chunks * tiles), 0);
  parallel_for(chunks, threads, [&](int64_t ch, int) {
    const int64_t end = std::min(visible, (ch + 1) * chunk_len);
    for (int64_t i = ch * chunk_len; i < end; ++i) count_tiles(i, cursor.data() + ch * tiles);
  });
  b.tile_start.assign(static_cast<size_t>(tiles + 1), 0);
  int64_t total = 0;
  for (int64_t t = 0; t < tiles; ++t) {
    b.tile_start[t] = total;
    for (int64_t ch = 0; ch < chunks; ++ch) {
      const int64_t count = cursor[ch * tiles + t];
      cursor[ch * tiles + t] = total;
      total += count;
    }
  }
  b.tile_start[tiles] = total;
  b.ids.assign(static_cast<size_t>(total), 0);
  parallel_for(chunks, threads, [&](int64_t ch, int) {
    int64_t* at = cursor.data() + ch * tiles;
    const int64_t end = std::min(visible, (ch + 1) * chunk_len);
    for (int64_t i = ch * chunk_len; i < end; ++i) {
      const Box& box = boxes[i];
      const int32_t* span = spans.data() + 2 * row_start[i];
      const int64_t cam_tile = b.rows[i] / s.gaussians * per_cam;
      for (int ty = box.ty0; ty < box.ty1; ++ty, span += 2) {
        const int64_t row_tile = cam_tile + static_cast<int64_t>(ty) * b.tiles_x;
        for (int tx = span[0]; tx <= span[1]; ++tx) b.ids[at[row_tile + tx]++] = static_cast<int32_t>(i);
      }
    }
  });
}

void composite_forward(const float* features, int channels, Binning& b, float* out,
                       int threads) {
#ifdef RS_HAVE_AVX2
  if (use_avx2()) return avx2::composite_forward(features, channels, b, out, threads);
#endif
  baseline::composite_forward(features, channels, b, out, threads);
}

void composite_backward(const float* opacities, int channels,
                        const Binning& b, const float* grad_out, float* grad_means2d,
                        float* grad_conics, float* grad_opacities, float* grad_features,
                        float* absgrad_means2d, int threads) {
#ifdef RS_HAVE_AVX2
  if (use_avx2())
    return avx2::composite_backward(opacities, channels, b, grad_out, grad_means2d,
                                    grad_conics, grad_opacities, grad_features,
                                    absgrad_means2d, threads);
#endif
  baseline::composite_backward(opacities, channels, b, grad_out, grad_means2d,
                               grad_conics, grad_opacities, grad_features, absgrad_means2d,
                               threads);
}

}  // namespace rs
