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
constexpr int kMaxChannels = 32;  // feature channels D of the compositing (checked by the module)

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
  double turn;                  // my + turn: y of the ellipse's leftmost point (- turn: rightmost)
  int32_t rx, ry;               // bounding-box half sizes (projection's radii)
  bool bounded;                 // false: conic not safely positive definite; no pruning
};

// Gaussian-tile lists and the per-pixel state the backward pass needs. The V visible
// Gaussians are numbered by rank: camera by camera, front to back (depth, then index), so
// a tile's list is its ranks in increasing order, and per-Gaussian data is laid out by
// rank (read in that order by the binning, and near each other by neighbouring tiles).
struct Binning {
  int tiles_x = 0, tiles_y = 0;
  int64_t cameras = 0, gaussians = 0;
  int width = 0, height = 0;
  std::vector<int32_t> rows;        // (V) rank -> row (cam * N + g)
  std::vector<Splat> splats;        // (V) by rank
  std::vector<int64_t> tile_start;  // (C * tiles + 1): list of tile t is [start[t], start[t+1])
  std::vector<int32_t> ids;         // ranks, front to back per tile
  std::vector<float> features;      // (V, D) by rank, gathered by the forward pass
  std::vector<float> t_final;       // (C, H, W) transmittance after the last contribution
  std::vector<int32_t> n_used;      // (C, H, W) list entries up to the last contribution
};

// Lists every visible Gaussian in each tile where its alpha > 1/255 ellipse reaches a pixel
// centre, front to back: by `depths` (C, N), ties by index.
void bin_splats(const Splats& s, const float* depths, int threads, Binning& b);

// Composites D feature channels plus alpha: out (C, H, W, D + 1). Fills b.t_final, b.n_used.
void composite_forward(const float* features, int channels, Binning& b, float* out,
                       int threads);

// Gradients of means2d (M, 2), conics (M, 3), opacities (M) and features (M, D) from the
// gradient of the output (C, H, W, D + 1), after composite_forward on the same binning;
// the gradient arrays must hold zeros. The opacities are those of the binning. When
// absgrad_means2d (M, 2) is not null, it gets the means' absolute gradient (AbsGS): the sum
// over pixels of each pixel's |contribution|, per axis.
void composite_backward(const float* opacities, int channels,
                        const Binning& b, const float* grad_out, float* grad_means2d,
                        float* grad_conics, float* grad_opacities, float* grad_features,
                        float* absgrad_means2d, int threads);

// Cameras of a projection: C views of one image size, each rendering a window of it.
struct Views {
  const float* viewmats = nullptr;    // (C, 4, 4) world to camera (OpenCV)
  const float* intrinsics = nullptr;  // (C, 3, 3)
  const float* offsets = nullptr;     // (C, 2) window origin (x0, y0) in the image
  int64_t cameras = 0;
  int width = 0, height = 0;                // the full image (sets the Jacobian clamp)
  int window_width = 0, window_height = 0;  // the rendered window (sets the culling)
  float near_plane = 0.01f, far_plane = 1e10f, eps2d = 0.3f;
};

// means (N, 3), quats (N, 4) w x y z, scales (N, 3), opacities (N,) -> means2d (C, N, 2),
// conics (C, N, 3), depths (C, N), radii (C, N, 2) (0: culled), as project_gaussians.
void project_forward(const float* means, const float* quats, const float* scales,
                     const float* opacities, int64_t n, const Views& v, float* means2d,
                     float* conics, float* depths, int32_t* radii, int threads);

// Adds the gradients of means, quats and scales from those of means2d, conics and depths.
void project_backward(const float* means, const float* quats, const float* scales, int64_t n,
                      const Views& v, const float* g_means2d, const float* g_conics,
                      const float* g_depths, float* g_means, float* g_quats, float* g_scales,
                      int threads);

// Which build of the compositing runs here: "avx2 (8 lanes)" or "baseline (4 lanes)".
const char* simd_name();

}  // namespace rs
