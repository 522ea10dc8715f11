// CPU rasterisation of projected 2D Gaussians: tile binning, front-to-back compositing and
// its backward pass. Plain C++17 with std::thread, no Python or torch headers: the Python
// module (module.cpp) passes the data pointers of contiguous float32 / int tensors.
//
// Conventions (those of rasterize_torch.py, gsplat and the 3DGS reference): pixel (row i,
// column j) has its centre at (j + 0.5, i + 0.5); sigma = (a dx^2 + c dy^2) / 2 + b dx dy
// with d = mean - pixel centre and conic (a, b, c); alpha = min(0.999, o exp(-sigma)),
// skipped unless alpha > 1/255; compositing stops before the Gaussian that would bring the
// transmittance to 1e-4 or below. The alpha output is composited like a feature of ones.
#pragma once

#include <cstdint>
#include <vector>

namespace rs {

constexpr int kTile = 16;  // binning and compositing tiles are kTile x kTile pixels
constexpr float kAlphaThreshold = 1.0f / 255.0f;
constexpr float kMaxAlpha = 0.999f;
constexpr float kMinTransmittance = 1e-4f;

// Projected Gaussians of C cameras x N Gaussians, flattened to M = C * N rows (row
// cam * N + g). Pointers are borrowed; every array is contiguous.
struct Splats {
  const float* means2d = nullptr;    // (M, 2) window pixels
  const float* conics = nullptr;     // (M, 3) inverse 2D covariance (a, b, c)
  const float* opacities = nullptr;  // (M,)
  const int32_t* radii = nullptr;    // (M, 2) bounding-box half sizes; 0: not visible
  int64_t cameras = 0;
  int64_t gaussians = 0;
  int width = 0;   // window size, the same for every camera
  int height = 0;
};

// One Gaussian as the compositing loops use it: the per-pixel alpha's inputs and its
// alpha > 1/255 ellipse {sigma < limit}, whose pixel row at centre y spans the columns
// x + 0.5 in xc -+ hw with dy = my - y, xc = mx + slope dy, hw^2 = k1 - k2 dy^2.
struct Splat {
  float mx, my, a, b, c, log_o;
  double slope, k1, k2, y_ext;  // y_ext: the ellipse's half height
  bool bounded;                 // false: conic not safely positive definite; no pruning
};

// Gaussian-tile lists (each depth-sorted) and the per-pixel state the backward pass needs.
struct Binning {
  int tiles_x = 0, tiles_y = 0;
  int64_t cameras = 0, gaussians = 0;
  int width = 0, height = 0;
  std::vector<int64_t> tile_start;  // (C * tiles + 1): list of tile t is [start[t], start[t+1])
  std::vector<int32_t> ids;         // Gaussian rows (cam * N + g), front to back per tile
  std::vector<Splat> splats;        // (M) filled for the listed Gaussians
  std::vector<float> t_final;       // (C, H, W) transmittance after the last contribution
  std::vector<int32_t> n_used;      // (C, H, W) list entries up to the last contribution
};

// Lists every visible Gaussian in each tile where its alpha > 1/255 ellipse reaches a pixel
// centre, in the order of `order` (C, N): each camera's Gaussian indices sorted by depth.
void bin_splats(const Splats& s, const int64_t* order, int threads, Binning& b);

// Composites D feature channels plus alpha: out (C, H, W, D + 1). Fills b.t_final, b.n_used.
void composite_forward(const float* features, int channels, Binning& b, float* out,
                       int threads);

// Gradients of means2d (M, 2), conics (M, 3), opacities (M) and features (M, D) from the
// gradient of the output (C, H, W, D + 1); the gradient arrays must hold zeros. The
// opacities and features are those of the forward pass.
void composite_backward(const float* opacities, const float* features, int channels,
                        const Binning& b, const float* grad_out, float* grad_means2d,
                        float* grad_conics, float* grad_opacities, float* grad_features,
                        int threads);

// Which build of the compositing runs here: "avx2 (8 lanes)" or "baseline (4 lanes)".
const char* simd_name();

}  // namespace rs
