// The compositing, forward and backward, for one vector width. kernel.cpp includes this file
// once per instruction set, with RS_LANES (pixels per vector) and RS_ISA (the namespace)
// defined, under that instruction set's target pragma: no include guard, on purpose, and
// nothing here may run at load time (a CPU without the instruction set must never
// execute it).

namespace rs {
namespace RS_ISA {

using detail::kPixels;
using detail::parallel_for;
using detail::row_range;
using detail::col_span;
using detail::TileBox;
using detail::tile_box;

namespace {

constexpr int kLanes = RS_LANES;
constexpr int kChunks = kPixels / kLanes;
static_assert(kTile % kLanes == 0, "a tile row is a whole number of chunks");

// kLanes pixels of a tile row. Comparisons give lane masks (-1 / 0), `mask ? a : b`
// selects per lane; every lane computes the same float operations as a scalar would.
typedef float FV __attribute__((vector_size(4 * kLanes)));
typedef int32_t IV __attribute__((vector_size(4 * kLanes)));
inline IV lane_index() {
  IV v;
  for (int j = 0; j < kLanes; ++j) v[j] = j;
  return v;
}

inline FV load(const float* p) {
  FV v;
  std::memcpy(&v, p, sizeof v);
  return v;
}
inline IV load(const int32_t* p) {
  IV v;
  std::memcpy(&v, p, sizeof v);
  return v;
}
inline void store(float* p, FV v) { std::memcpy(p, &v, sizeof v); }
inline void store(int32_t* p, IV v) { std::memcpy(p, &v, sizeof v); }
inline FV splat(float x) { return FV{} + x; }
inline IV splat(int32_t x) { return IV{} + x; }
inline float lane_sum(FV v) {
  float total = 0.0f;
  for (int j = 0; j < kLanes; ++j) total += v[j];
  return total;
}
inline int lane_count(IV mask) {
  int n = 0;
  for (int j = 0; j < kLanes; ++j) n -= mask[j];
  return n;
}

// exp(x) for x in [-20, 1] (Cephes' expf: range reduction and a degree-6 polynomial,
// ~1 ulp) in plain vector arithmetic: every lane, pass and instruction set gives the same
// bits, so the forward and backward passes agree on each alpha.
inline FV exp_poly(FV x) {
  const float shifter = 12582912.0f;  // 1.5 * 2^23: adding it rounds to the nearest integer
  const FV fn = (x * 1.44269504088896341f + shifter) - shifter;
  FV r = x - fn * 0.693359375f;
  r = r - fn * -2.12194440e-4f;
  FV q = splat(1.9875691500e-4f);
  q = q * r + 1.3981999507e-3f;
  q = q * r + 8.3334519073e-3f;
  q = q * r + 4.1665795894e-2f;
  q = q * r + 1.6666665459e-1f;
  q = q * r + 5.0000001201e-1f;
  q = q * (r * r) + r + 1.0f;
  const IV bits = (__builtin_convertvector(fn, IV) + 127) << 23;
  FV scale;  // 2^n
  std::memcpy(&scale, &bits, sizeof scale);
  return q * scale;
}

// alpha before the clamp, with the torch path's float32 expression and order:
// exp(max(log(o) - a dx^2 / 2 - c dy^2 / 2 - b dx dy, -20)); row_term = -c dy^2 / 2.
inline FV raw_alpha(const Splat& p, FV dx, float dy, float row_term) {
  FV e = (p.log_o - 0.5f * p.a * dx * dx) + row_term + (-p.b * dx) * dy;
  e = e < -20.0f ? splat(-20.0f) : e;
  e = e > 1.0f ? splat(1.0f) : e;  // sigma < 0 only for a conic that is not positive definite
  return exp_poly(e);
}

}  // namespace

void composite_forward(const float* features, int channels, Binning& b, float* out,
                       int threads) {
  const int dp = channels + 1;
  const int64_t tiles = static_cast<int64_t>(b.tile_start.size()) - 1;
  const size_t pixels = static_cast<size_t>(b.cameras) * b.width * b.height;
  b.t_final.assign(pixels, 1.0f);
  b.n_used.assign(pixels, 0);
  const int workers = std::max(1, threads);
  std::vector<std::vector<float>> scratch(workers);
  std::vector<std::vector<int32_t>> scratch_ints(workers);
  parallel_for(tiles, workers, [&](int64_t tile, int worker) {
    const TileBox box = tile_box(b, tile);
    const IV lane = lane_index();
    std::vector<float>& buf = scratch[worker];
    buf.assign(static_cast<size_t>(kPixels) * (dp + 1) + kTile, 0.0f);
    float* trans = buf.data();          // (pixels) transmittance
    float* acc = trans + kPixels;       // (D + 1, pixels) features and alpha
    float* cx = acc + kPixels * dp;     // (kTile) pixel-centre x of the tile's columns
    std::vector<int32_t>& ints = scratch_ints[worker];
    ints.assign(2 * kPixels, 0);
    int32_t* used = ints.data();        // (pixels) list entries up to the last contribution
    int32_t* alive = used + kPixels;    // (pixels) -1: still compositing, 0: done or outside
    int chunk_alive[kChunks] = {};
    for (int r = 0; r < kTile; ++r) {
      for (int col = 0; col < kTile; ++col) {
        const bool in = r < box.h && col < box.w;
        trans[r * kTile + col] = 1.0f;
        alive[r * kTile + col] = in ? -1 : 0;
        chunk_alive[(r * kTile + col) / kLanes] += in;
      }
    }
    for (int col = 0; col < kTile; ++col) cx[col] = static_cast<float>(box.x0 + col) + 0.5f;
    int64_t n_alive = static_cast<int64_t>(box.w) * box.h;
    const int64_t start = b.tile_start[tile], end = b.tile_start[tile + 1];
    for (int64_t k = start; k < end && n_alive > 0; ++k) {
      const int64_t row = b.ids[k];
      const Splat& p = b.splats[row];
      const float* f = features + row * channels;
      const IV rank = splat(static_cast<int32_t>(k - start + 1));
      int r0, r1;
      if (!row_range(p, box.y0, box.h, r0, r1)) continue;
      for (int r = r0; r <= r1; ++r) {
        const float yc = static_cast<float>(box.y0 + r) + 0.5f;
        int lo, hi;
        if (!col_span(p, yc, box.x0, box.x0 + box.w - 1, lo, hi)) continue;
        lo -= box.x0;
        hi -= box.x0;
        const float dy = p.my - yc;
        const float row_term = -0.5f * p.c * dy * dy;
        for (int cs = lo - lo % kLanes; cs <= hi; cs += kLanes) {
          const int base = r * kTile + cs;
          if (!chunk_alive[base / kLanes]) continue;
          const FV raw = raw_alpha(p, p.mx - load(cx + cs), dy, row_term);
          const IV col = lane + cs;
          const IV in = (col >= lo) & (col <= hi) & load(alive + base) & (raw > kAlphaThreshold);
          const FV alpha = raw > kMaxAlpha ? splat(kMaxAlpha) : raw;
          const FV t = load(trans + base);
          const FV t_next = t * (1.0f - alpha);
          const IV done = in & (t_next <= kMinTransmittance);  // stops before this Gaussian
          const IV take = in & ~done;
          const FV w = take ? t * alpha : FV{};
          store(trans + base, take ? t_next : t);
          store(alive + base, load(alive + base) & ~done);
          store(used + base, take ? rank : load(used + base));
          for (int d = 0; d < channels; ++d) {
            float* a = acc + d * kPixels + base;
            store(a, load(a) + w * f[d]);
          }
          float* a = acc + channels * kPixels + base;
          store(a, load(a) + w);
          const int finished = lane_count(done);
          chunk_alive[base / kLanes] -= finished;
          n_alive -= finished;
        }
      }
    }
    for (int r = 0; r < box.h; ++r) {
      for (int col = 0; col < box.w; ++col) {
        const int px = r * kTile + col;
        const size_t at = (static_cast<size_t>(box.cam) * b.height + box.y0 + r) * b.width + box.x0 + col;
        for (int d = 0; d < dp; ++d) out[at * dp + d] = acc[d * kPixels + px];
        b.t_final[at] = trans[px];
        b.n_used[at] = used[px];
      }
    }
  });
}

void composite_backward(const float* opacities, const float* features, int channels,
                        const Binning& b, const float* grad_out, float* grad_means2d,
                        float* grad_conics, float* grad_opacities, float* grad_features,
                        int threads) {
  const int dp = channels + 1;
  const int64_t tiles = static_cast<int64_t>(b.tile_start.size()) - 1;
  const int64_t m = b.cameras * b.gaussians;
  const int64_t stride = 6 + channels;  // per Gaussian: means 2, conics 3, opacity 1, features
  // Worker 0 adds into the outputs, the others into private arrays summed at the end (no
  // atomics); fewer workers when those would take more than 1 GiB.
  const int64_t per_worker = std::max<int64_t>(1, m * stride * int64_t{sizeof(float)});
  const int workers = static_cast<int>(std::max<int64_t>(
      1, std::min<int64_t>({int64_t{std::max(1, threads)}, tiles, 1 + (int64_t{1} << 30) / per_worker})));
  std::vector<std::vector<float>> private_grads(workers);
  for (int w = 1; w < workers; ++w) private_grads[w].assign(static_cast<size_t>(m * stride), 0.0f);
  struct Grads {
    float *means, *conics, *opac, *feat;
  };
  auto grads_of = [&](int worker) {
    if (worker == 0) return Grads{grad_means2d, grad_conics, grad_opacities, grad_features};
    float* base = private_grads[worker].data();
    return Grads{base, base + 2 * m, base + 5 * m, base + 6 * m};
  };
  std::vector<std::vector<float>> scratch(workers);
  std::vector<std::vector<int32_t>> scratch_used(workers);
  const int ran = parallel_for(tiles, workers, [&](int64_t tile, int worker) {
    const TileBox box = tile_box(b, tile);
    const int64_t start = b.tile_start[tile];
    if (b.tile_start[tile + 1] == start) return;
    const IV lane = lane_index();
    std::vector<float>& buf = scratch[worker];
    buf.assign(static_cast<size_t>(kPixels) * (dp + 2) + kTile + static_cast<size_t>(kLanes) * channels, 0.0f);
    float* trans = buf.data();          // (pixels) transmittance, walked back towards 1
    float* suffix = trans + kPixels;    // (pixels) sum over later Gaussians of w (g . f)
    float* g = suffix + kPixels;        // (D + 1, pixels) gradient of the output
    float* cx = g + kPixels * dp;       // (kTile) pixel-centre x of the tile's columns
    float* lane_f = cx + kTile;         // (D, kLanes) one Gaussian's feature gradient per lane
    std::vector<int32_t>& used = scratch_used[worker];
    used.assign(kPixels, 0);
    int32_t chunk_used[kChunks] = {};
    for (int r = 0; r < box.h; ++r) {
      for (int col = 0; col < box.w; ++col) {
        const int px = r * kTile + col;
        const size_t at = (static_cast<size_t>(box.cam) * b.height + box.y0 + r) * b.width + box.x0 + col;
        trans[px] = b.t_final[at];
        used[px] = b.n_used[at];
        chunk_used[px / kLanes] = std::max(chunk_used[px / kLanes], used[px]);
        for (int d = 0; d < dp; ++d) g[d * kPixels + px] = grad_out[at * dp + d];
      }
    }
    for (int col = 0; col < kTile; ++col) cx[col] = static_cast<float>(box.x0 + col) + 0.5f;
    const int32_t most = *std::max_element(chunk_used, chunk_used + kChunks);
    const Grads out = grads_of(worker);
    for (int32_t kk = most - 1; kk >= 0; --kk) {
      const int64_t row = b.ids[start + kk];
      const Splat& p = b.splats[row];
      const float* f = features + row * channels;
      int r0, r1;
      if (!row_range(p, box.y0, box.h, r0, r1)) continue;
      const IV rank = splat(kk);
      FV l_mx{}, l_my{}, l_ca{}, l_cb{}, l_cc{}, l_op{};  // per-lane sums of the gradients
      std::fill(lane_f, lane_f + kLanes * channels, 0.0f);
      bool touched = false;
      for (int r = r0; r <= r1; ++r) {
        const float yc = static_cast<float>(box.y0 + r) + 0.5f;
        int lo, hi;
        if (!col_span(p, yc, box.x0, box.x0 + box.w - 1, lo, hi)) continue;
        lo -= box.x0;
        hi -= box.x0;
        const float dy = p.my - yc;
        const float row_term = -0.5f * p.c * dy * dy;
        for (int cs = lo - lo % kLanes; cs <= hi; cs += kLanes) {
          const int base = r * kTile + cs;
          if (chunk_used[base / kLanes] <= kk) continue;
          touched = true;
          FV g_dot_f = load(g + channels * kPixels + base);  // the alpha channel: f = 1
          for (int d = 0; d < channels; ++d) g_dot_f += load(g + d * kPixels + base) * f[d];
          const FV dx = p.mx - load(cx + cs);
          const FV raw = raw_alpha(p, dx, dy, row_term);
          const IV col = lane + cs;
          const IV in = (col >= lo) & (col <= hi) & (rank < load(used.data() + base)) &
                        (raw > kAlphaThreshold);
          const FV alpha = raw > kMaxAlpha ? splat(kMaxAlpha) : raw;
          const FV one_minus = 1.0f - alpha;
          const FV t_after = load(trans + base);
          const FV t = in ? t_after / one_minus : t_after;  // transmittance before this one
          store(trans + base, t);
          const FV weight = alpha * t;
          const FV later = load(suffix + base);
          // dL/dalpha = T_before (g . f) - (sum over later Gaussians of w (g . f)) / (1 - alpha)
          const FV g_alpha = t * g_dot_f - later / one_minus;
          store(suffix + base, in ? later + weight * g_dot_f : later);
          const FV w = in ? weight : FV{};
          // alpha = o exp(-sigma) where the clamp is not active: dL/d(-sigma) = dL/dalpha alpha
          const FV g_ns = in & (raw < kMaxAlpha) ? g_alpha * alpha : FV{};
          l_op += g_ns;  // divided by the opacity at the end
          l_mx -= g_ns * (p.a * dx + p.b * dy);
          l_my -= g_ns * (p.b * dx + p.c * dy);
          l_ca -= 0.5f * g_ns * dx * dx;
          l_cb -= g_ns * dx * dy;
          l_cc -= 0.5f * g_ns * dy * dy;
          for (int d = 0; d < channels; ++d) {
            float* lf = lane_f + d * kLanes;
            store(lf, load(lf) + w * load(g + d * kPixels + base));
          }
        }
      }
      if (!touched) continue;
      out.means[2 * row] += lane_sum(l_mx);
      out.means[2 * row + 1] += lane_sum(l_my);
      out.conics[3 * row] += lane_sum(l_ca);
      out.conics[3 * row + 1] += lane_sum(l_cb);
      out.conics[3 * row + 2] += lane_sum(l_cc);
      out.opac[row] += lane_sum(l_op);
      for (int d = 0; d < channels; ++d)
        out.feat[row * channels + d] += lane_sum(load(lane_f + d * kLanes));
    }
  });
  const int64_t block = 1 << 14;
  parallel_for((m + block - 1) / block, workers, [&](int64_t blk, int) {
    const int64_t lo = blk * block, hi = std::min(m, lo + block);
    for (int w = 1; w < ran; ++w) {
      const Grads o = grads_of(w);
      for (int64_t i = 2 * lo; i < 2 * hi; ++i) grad_means2d[i] += o.means[i];
      for (int64_t i = 3 * lo; i < 3 * hi; ++i) grad_conics[i] += o.conics[i];
      for (int64_t i = lo; i < hi; ++i) grad_opacities[i] += o.opac[i];
      for (int64_t i = lo * channels; i < hi * channels; ++i) grad_features[i] += o.feat[i];
    }
    // dL/do = dL/d(-sigma) / o (alpha = o exp(-sigma))
    for (int64_t i = lo; i < hi; ++i) grad_opacities[i] /= std::max(opacities[i], 1e-30f);
  });
}

}  // namespace RS_ISA
}  // namespace rs
