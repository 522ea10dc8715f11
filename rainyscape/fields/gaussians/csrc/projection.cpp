// EWA projection of 3D Gaussians, forward and backward: the float32 counterpart of
// projection.project_gaussians (same formulas and conventions; see that docstring).
#include <algorithm>
#include <cmath>

#include "kernel.h"
#include "kernel_common.h"

namespace rs {
namespace {

constexpr float kMaxExtentSigma = 3.33f;

struct Camera {
  float r[9], t[3];  // world-to-camera rotation (row major) and translation
  float fx, fy, cx, cy;
  float x0, y0;      // window origin in the image
  float lim_lo_x, lim_hi_x, lim_lo_y, lim_hi_y;  // clamp of x / z and y / z for the Jacobian
};

Camera camera(const Views& v, int64_t c) {
  Camera cam;
  const float* m = v.viewmats + 16 * c;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) cam.r[3 * i + j] = m[4 * i + j];
    cam.t[i] = m[4 * i + 3];
  }
  const float* k = v.intrinsics + 9 * c;
  cam.fx = k[0];
  cam.fy = k[4];
  cam.cx = k[2];
  cam.cy = k[5];
  cam.x0 = v.offsets[2 * c];
  cam.y0 = v.offsets[2 * c + 1];
  const float lim_x = 0.3f * 0.5f * static_cast<float>(v.width) / cam.fx;
  const float lim_y = 0.3f * 0.5f * static_cast<float>(v.height) / cam.fy;
  cam.lim_lo_x = -(cam.cx / cam.fx + lim_x);
  cam.lim_hi_x = (static_cast<float>(v.width) - cam.cx) / cam.fx + lim_x;
  cam.lim_lo_y = -(cam.cy / cam.fy + lim_y);
  cam.lim_hi_y = (static_cast<float>(v.height) - cam.cy) / cam.fy + lim_y;
  return cam;
}

// Rotation of the normalised quaternion (w, x, y, z), row major; `inv_norm`: 1 / |q|.
void rotation(const float* q, float* rot, float* unit, float& inv_norm) {
  const float norm = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  inv_norm = 1.0f / std::max(norm, 1e-12f);
  for (int i = 0; i < 4; ++i) unit[i] = q[i] * inv_norm;
  const float w = unit[0], x = unit[1], y = unit[2], z = unit[3];
  rot[0] = 1 - 2 * (y * y + z * z);
  rot[1] = 2 * (x * y - w * z);
  rot[2] = 2 * (x * z + w * y);
  rot[3] = 2 * (x * y + w * z);
  rot[4] = 1 - 2 * (x * x + z * z);
  rot[5] = 2 * (y * z - w * x);
  rot[6] = 2 * (x * z - w * y);
  rot[7] = 2 * (y * z + w * x);
  rot[8] = 1 - 2 * (x * x + y * y);
}

// The quantities of one Gaussian in one camera that the forward pass produces and the
// backward pass differentiates.
struct Projected {
  float x, y, z, z_safe, xz, yz, tx, ty;
  bool in_depth, clamp_x, clamp_y;  // clamp_*: the Jacobian's t is clamped (no gradient)
  float row_x[3], row_y[3];         // rows of J W
  float ax[3], ay[3];               // rows of J W M
  float cov_a, cov_b, cov_c, det;
};

void project_one(const Camera& cam, const float* mean, const float* m, float eps2d,
                 float near_plane, float far_plane, Projected& p) {
  const float* r = cam.r;
  p.x = r[0] * mean[0] + r[1] * mean[1] + r[2] * mean[2] + cam.t[0];
  p.y = r[3] * mean[0] + r[4] * mean[1] + r[5] * mean[2] + cam.t[1];
  p.z = r[6] * mean[0] + r[7] * mean[1] + r[8] * mean[2] + cam.t[2];
  p.in_depth = p.z > near_plane && p.z < far_plane;
  p.z_safe = p.in_depth ? p.z : 1.0f;
  p.xz = p.x / p.z_safe;
  p.yz = p.y / p.z_safe;
  p.tx = std::min(std::max(p.xz, cam.lim_lo_x), cam.lim_hi_x);
  p.ty = std::min(std::max(p.yz, cam.lim_lo_y), cam.lim_hi_y);
  p.clamp_x = !(p.xz >= cam.lim_lo_x && p.xz <= cam.lim_hi_x);
  p.clamp_y = !(p.yz >= cam.lim_lo_y && p.yz <= cam.lim_hi_y);
  const float sx = cam.fx / p.z_safe, sy = cam.fy / p.z_safe;
  for (int i = 0; i < 3; ++i) {
    p.row_x[i] = sx * (r[i] - p.tx * r[6 + i]);
    p.row_y[i] = sy * (r[3 + i] - p.ty * r[6 + i]);
  }
  for (int j = 0; j < 3; ++j) {
    p.ax[j] = p.row_x[0] * m[j] + p.row_x[1] * m[3 + j] + p.row_x[2] * m[6 + j];
    p.ay[j] = p.row_y[0] * m[j] + p.row_y[1] * m[3 + j] + p.row_y[2] * m[6 + j];
  }
  p.cov_a = p.ax[0] * p.ax[0] + p.ax[1] * p.ax[1] + p.ax[2] * p.ax[2] + eps2d;
  p.cov_b = p.ax[0] * p.ay[0] + p.ax[1] * p.ay[1] + p.ax[2] * p.ay[2];
  p.cov_c = p.ay[0] * p.ay[0] + p.ay[1] * p.ay[1] + p.ay[2] * p.ay[2] + eps2d;
  p.det = p.cov_a * p.cov_c - p.cov_b * p.cov_b;
}

}  // namespace

void project_forward(const float* means, const float* quats, const float* scales,
                     const float* opacities, int64_t n, const Views& v, float* means2d,
                     float* conics, float* depths, int32_t* radii, int threads) {
  std::vector<Camera> cams;
  for (int64_t c = 0; c < v.cameras; ++c) cams.push_back(camera(v, c));
  const int64_t block = 1024;
  detail::parallel_for((n + block - 1) / block, threads, [&](int64_t blk, int) {
    for (int64_t g = blk * block; g < std::min(n, (blk + 1) * block); ++g) {
      float rot[9], unit[4], inv_norm, m[9];
      rotation(quats + 4 * g, rot, unit, inv_norm);
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) m[3 * i + j] = rot[3 * i + j] * scales[3 * g + j];
      const float o = opacities[g];
      // Opacity-aware extent: alpha >= 1/255 within `extent` standard deviations.
      const float extent = std::min(
          std::sqrt(2.0f * std::log(std::max(o / kAlphaThreshold, 1.0f))), kMaxExtentSigma);
      for (int64_t c = 0; c < v.cameras; ++c) {
        const Camera& cam = cams[c];
        Projected p;
        project_one(cam, means + 3 * g, m, v.eps2d, v.near_plane, v.far_plane, p);
        const int64_t row = c * n + g;
        const float mx = cam.fx * p.xz + cam.cx - cam.x0, my = cam.fy * p.yz + cam.cy - cam.y0;
        means2d[2 * row] = mx;
        means2d[2 * row + 1] = my;
        depths[row] = p.z;
        const bool det_ok = p.det > 0;
        const float det_safe = det_ok ? p.det : 1.0f;
        conics[3 * row] = p.cov_c / det_safe;
        conics[3 * row + 1] = -p.cov_b / det_safe;
        conics[3 * row + 2] = p.cov_a / det_safe;
        const float rx = std::ceil(extent * std::sqrt(p.cov_a));
        const float ry = std::ceil(extent * std::sqrt(p.cov_c));
        const bool on_screen = mx + rx > 0 && mx - rx < v.window_width && my + ry > 0 &&
                               my - ry < v.window_height;
        const bool keep = p.in_depth && det_ok && o >= kAlphaThreshold && (rx > 0 || ry > 0) &&
                          on_screen;
        radii[2 * row] = keep ? static_cast<int32_t>(rx) : 0;
        radii[2 * row + 1] = keep ? static_cast<int32_t>(ry) : 0;
      }
    }
  });
}

void project_backward(const float* means, const float* quats, const float* scales, int64_t n,
                      const Views& v, const float* g_means2d, const float* g_conics,
                      const float* g_depths, float* g_means, float* g_quats, float* g_scales,
                      int threads) {
  std::vector<Camera> cams;
  for (int64_t c = 0; c < v.cameras; ++c) cams.push_back(camera(v, c));
  const int64_t block = 1024;
  detail::parallel_for((n + block - 1) / block, threads, [&](int64_t blk, int) {
    for (int64_t g = blk * block; g < std::min(n, (blk + 1) * block); ++g) {
      float rot[9], unit[4], inv_norm, m[9];
      rotation(quats + 4 * g, rot, unit, inv_norm);
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) m[3 * i + j] = rot[3 * i + j] * scales[3 * g + j];
      float gm[9] = {}, gmean[3] = {};
      for (int64_t c = 0; c < v.cameras; ++c) {
        const Camera& cam = cams[c];
        const int64_t row = c * n + g;
        Projected p;
        project_one(cam, means + 3 * g, m, v.eps2d, v.near_plane, v.far_plane, p);
        float gx = 0, gy = 0, gz = g_depths[row];  // camera-space point
        // means2d = (fx x / z + cx - x0, fy y / z + cy - y0)
        float g_xz = cam.fx * g_means2d[2 * row], g_yz = cam.fy * g_means2d[2 * row + 1];
        // conic = inverse of [[a, b], [b, c]]: dL/dSigma = -Q G Q, G with halved off-diagonal
        float ga = 0, gb = 0, gc = 0;
        if (p.det > 0) {
          const float q0 = p.cov_c / p.det, q1 = -p.cov_b / p.det, q2 = p.cov_a / p.det;
          const float g0 = g_conics[3 * row], g1 = 0.5f * g_conics[3 * row + 1],
                      g2 = g_conics[3 * row + 2];
          // (Q G Q) entries for symmetric Q = [[q0, q1], [q1, q2]], G = [[g0, g1], [g1, g2]]
          const float t00 = q0 * g0 + q1 * g1, t01 = q0 * g1 + q1 * g2;
          const float t10 = q1 * g0 + q2 * g1, t11 = q1 * g1 + q2 * g2;
          ga = -(t00 * q0 + t01 * q1);
          gb = -2.0f * (t00 * q1 + t01 * q2);
          gc = -(t10 * q1 + t11 * q2);
        } else {  // conic = (c, -b, a) with det replaced by 1 (never visible)
          ga = g_conics[3 * row + 2];
          gb = -g_conics[3 * row + 1];
          gc = g_conics[3 * row];
        }
        // cov_a = ax . ax + eps, cov_b = ax . ay, cov_c = ay . ay + eps
        float g_ax[3], g_ay[3];
        for (int j = 0; j < 3; ++j) {
          g_ax[j] = 2.0f * ga * p.ax[j] + gb * p.ay[j];
          g_ay[j] = 2.0f * gc * p.ay[j] + gb * p.ax[j];
        }
        // ax = row_x M, ay = row_y M
        float g_rx[3], g_ry[3];
        for (int i = 0; i < 3; ++i) {
          g_rx[i] = g_ax[0] * m[3 * i] + g_ax[1] * m[3 * i + 1] + g_ax[2] * m[3 * i + 2];
          g_ry[i] = g_ay[0] * m[3 * i] + g_ay[1] * m[3 * i + 1] + g_ay[2] * m[3 * i + 2];
          for (int j = 0; j < 3; ++j) gm[3 * i + j] += p.row_x[i] * g_ax[j] + p.row_y[i] * g_ay[j];
        }
        // row_x = (fx / z) (w0 - tx w2), row_y = (fy / z) (w1 - ty w2)
        const float* r = cam.r;
        float g_sx = 0, g_sy = 0, g_tx = 0, g_ty = 0;
        for (int i = 0; i < 3; ++i) {
          g_sx += g_rx[i] * (r[i] - p.tx * r[6 + i]);
          g_sy += g_ry[i] * (r[3 + i] - p.ty * r[6 + i]);
          g_tx -= g_rx[i] * r[6 + i];
          g_ty -= g_ry[i] * r[6 + i];
        }
        const float sx = cam.fx / p.z_safe, sy = cam.fy / p.z_safe;
        g_tx *= sx;
        g_ty *= sy;
        if (!p.clamp_x) g_xz += g_tx;
        if (!p.clamp_y) g_yz += g_ty;
        if (p.in_depth) {  // z_safe = z: fx / z, x / z and y / z depend on z
          gz -= (g_sx * sx + g_sy * sy) / p.z;
          gz -= (g_xz * p.xz + g_yz * p.yz) / p.z;
        }
        gx += g_xz / p.z_safe;
        gy += g_yz / p.z_safe;
        // p = R mean + t
        for (int j = 0; j < 3; ++j) gmean[j] += r[j] * gx + r[3 + j] * gy + r[6 + j] * gz;
      }
      for (int j = 0; j < 3; ++j) g_means[3 * g + j] += gmean[j];
      // M = R diag(s)
      float g_rot[9];
      for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) {
          g_rot[3 * i + j] = gm[3 * i + j] * scales[3 * g + j];
          g_scales[3 * g + j] += gm[3 * i + j] * rot[3 * i + j];
        }
      }
      // R of the unit quaternion (w, x, y, z), then its normalisation
      const float w = unit[0], x = unit[1], y = unit[2], z = unit[3];
      const float* d = g_rot;
      float gu[4];
      gu[0] = 2 * (-z * d[1] + y * d[2] + z * d[3] - x * d[5] - y * d[6] + x * d[7]);
      gu[1] = 2 * (y * d[1] + z * d[2] + y * d[3] - 2 * x * d[4] - w * d[5] + z * d[6] +
                   w * d[7] - 2 * x * d[8]);
      gu[2] = 2 * (-2 * y * d[0] + x * d[1] + w * d[2] + x * d[3] + z * d[5] - w * d[6] +
                   z * d[7] - 2 * y * d[8]);
      gu[3] = 2 * (-2 * z * d[0] - w * d[1] + x * d[2] + w * d[3] - 2 * z * d[4] + y * d[5] +
                   x * d[6] + y * d[7]);
      const float dot = gu[0] * unit[0] + gu[1] * unit[1] + gu[2] * unit[2] + gu[3] * unit[3];
      const float norm = std::sqrt(quats[4 * g] * quats[4 * g] + quats[4 * g + 1] * quats[4 * g + 1] +
                                   quats[4 * g + 2] * quats[4 * g + 2] + quats[4 * g + 3] * quats[4 * g + 3]);
      for (int i = 0; i < 4; ++i)  // normalize(q) = q / max(|q|, eps)
        g_quats[4 * g + i] += norm > 1e-12f ? (gu[i] - unit[i] * dot) * inv_norm : gu[i] * inv_norm;
    }
  });
}

}  // namespace rs
