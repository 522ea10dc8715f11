// Internal helpers of the kernel shared by the binning and by every instruction-set build of
// the compositing (composite_impl.h): threads, the per-Gaussian ellipse and its spans.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstring>
#include <exception>
#include <limits>
#include <stdexcept>

#include "kernel.h"
#include "parallel.h"

namespace rs {
namespace detail {

constexpr int kPixels = kTile * kTile;

inline Splat make_splat(const Splats& s, int64_t row) {
  Splat p;
  p.mx = s.means2d[2 * row];
  p.my = s.means2d[2 * row + 1];
  p.a = s.conics[3 * row];
  p.b = s.conics[3 * row + 1];
  p.c = s.conics[3 * row + 2];
  const float o = s.opacities[row];
  p.log_o = std::log(o);
  p.rx = s.radii[2 * row];
  p.ry = s.radii[2 * row + 1];
  const double a = p.a, b = p.b, c = p.c;
  const double det = a * c - b * b;
  const double lambda_min = 0.5 * (a + c) - std::sqrt(0.25 * (a - c) * (a - c) + b * b);
  const double limit = std::log(static_cast<double>(o) * 255.0);  // alpha > 1/255 <=> sigma < limit
  p.bounded = a > 0 && c > 0 && det > 0 && lambda_min > 0 && std::isfinite(a + b + c) &&
              std::isfinite(limit) && std::isfinite(static_cast<double>(p.mx) + p.my);
  if (!p.bounded) {
    p.slope = p.k1 = p.k2 = p.turn = 0.0;
    p.y_ext = std::numeric_limits<double>::infinity();
    return p;
  }
  // A margin for the float32 rounding of a pixel's sigma: ~1e-7 of the sum of its terms'
  // magnitudes, at most ~limit (a + c) / lambda_min on the ellipse (large when slender).
  const double bound = std::max(
      0.0, limit + 1e-3 + 1e-6 * (std::fabs(limit) + 1.0) * (a + c) / lambda_min);
  p.slope = b / a;
  p.k1 = 2.0 * bound / a;
  p.k2 = det / (a * a);
  p.y_ext = std::sqrt(2.0 * bound * a / det);
  // The leftmost point has d sigma / d dy = 0: dy = -(b / c) dx at dx = sqrt(2 bound c / det).
  p.turn = p.slope / (p.k2 + p.slope * p.slope) * std::sqrt(p.k1 * (1.0 + p.slope * p.slope / p.k2));
  return p;
}

// Local rows [r0, r1] of a tile (origin row y0, h rows) that the ellipse may reach.
inline bool row_range(const Splat& p, int y0, int h, int& r0, int& r1) {
  double lo = 0, hi = h - 1;
  if (p.bounded) {
    lo = std::max(lo, std::ceil(p.my - p.y_ext - 0.5) - y0);
    hi = std::min(hi, std::floor(p.my + p.y_ext - 0.5) - y0);
  }
  if (!(lo <= hi)) return false;
  r0 = static_cast<int>(lo);
  r1 = static_cast<int>(hi);
  return true;
}

struct TileBox {
  int64_t cam;
  int x0, y0, w, h;  // window pixels of the tile (clipped to the window)
};

inline TileBox tile_box(const Binning& b, int64_t tile) {
  const int64_t per_cam = static_cast<int64_t>(b.tiles_x) * b.tiles_y;
  const int64_t t = tile % per_cam;
  TileBox box;
  box.cam = tile / per_cam;
  box.x0 = static_cast<int>(t % b.tiles_x) * kTile;
  box.y0 = static_cast<int>(t / b.tiles_x) * kTile;
  box.w = std::min(kTile, b.width - box.x0);
  box.h = std::min(kTile, b.height - box.y0);
  return box;
}

}  // namespace detail
}  // namespace rs
