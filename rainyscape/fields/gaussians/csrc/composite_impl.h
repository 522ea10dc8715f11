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
using detail::TileBox;
using detail::tile_box;

namespace {

constexpr int kLanes = RS_LANES;
static_assert(kTile % kLanes == 0 && kTile >= kLanes, "a tile row holds whole vectors");

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
inline FV abs_lanes(FV x) { return x < FV{} ? -x : x; }
inline IV splat(int32_t x) { return IV{} + x; }
// Sum of the lanes, halving the vector each step (shuffles instead of kLanes extracts).
#if defined(__clang__)
#define RS_SHUFFLE(v, ...) __builtin_shufflevector(v, v, __VA_ARGS__)
#else
#define RS_SHUFFLE(v, ...) __builtin_shuffle(v, IV{__VA_ARGS__})
#endif
inline float lane_sum(FV v) {
#if RS_LANES == 8
  v += RS_SHUFFLE(v, 4, 5, 6, 7, 0, 1, 2, 3);
  v += RS_SHUFFLE(v, 2, 3, 0, 1, 6, 7, 4, 5);
  v += RS_SHUFFLE(v, 1, 0, 3, 2, 5, 4, 7, 6);
#elif RS_LANES == 4
  v += RS_SHUFFLE(v, 2, 3, 0, 1);
  v += RS_SHUFFLE(v, 1, 0, 3, 2);
#else
#error "RS_LANES must be 4 or 8"
#endif
  return v[0];
}
#undef RS_SHUFFLE
// Bit j set where lane j of the mask is set.
inline unsigned lane_bits(IV mask) {
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && RS_LANES == 8
  return static_cast<unsigned>(__builtin_ia32_movmskps256(reinterpret_cast<FV>(mask)));
#elif defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && RS_LANES == 4
  return static_cast<unsigned>(__builtin_ia32_movmskps(reinterpret_cast<FV>(mask)));
#else
  unsigned bits = 0;
  for (int j = 0; j < kLanes; ++j) bits |= (mask[j] ? 1u : 0u) << j;
  return bits;
#endif
}
inline int lane_count(IV mask) { return __builtin_popcount(lane_bits(mask)); }

// Asks for the Splat and features of a list entry a few entries ahead: a tile's list jumps
// across the whole table, and without this each entry starts with a cache miss.
constexpr int kPrefetch = 8;
inline void prefetch_entry(const Binning& b, int64_t k, int channels) {
#if defined(__GNUC__)
  const int64_t id = b.ids[k];
  __builtin_prefetch(&b.splats[id]);
  __builtin_prefetch(reinterpret_cast<const char*>(&b.splats[id]) + 64);
  __builtin_prefetch(b.features.data() + id * channels);
#else
  (void)b, (void)k, (void)channels;
#endif
}

// Tile-local column spans [lo[r], hi[r]] of rows r0..r1 that the ellipse reaches (lo > hi:
// none): pixel centres x + 0.5 within xc -+ hw (kernel.h, Splat). Computed for all rows
// before the pixel work, so that their square roots overlap instead of each waiting in line.
inline void tile_spans(const Splat& p, const TileBox& box, int r0, int r1, int32_t* lo,
                       int32_t* hi) {
  if (!p.bounded) {
    for (int r = r0; r <= r1; ++r) lo[r] = 0, hi[r] = box.w - 1;
    return;
  }
  const double mx = static_cast<double>(p.mx) - box.x0, my = static_cast<double>(p.my) - box.y0;
  const double right = box.w - 1;
  for (int r = r0; r <= r1; ++r) {
    const double dy = my - (r + 0.5);
    const double h2 = p.k1 - p.k2 * dy * dy;
    const double hw = std::sqrt(std::max(h2, 0.0)), xc = mx + p.slope * dy;
    const double xl = std::min(std::max(std::ceil(xc - hw - 0.5), 0.0), right + 1);
    const double xh = std::min(std::max(std::floor(xc + hw - 0.5), -1.0), right);
    lo[r] = h2 >= 0 ? static_cast<int32_t>(xl) : 1;
    hi[r] = h2 >= 0 ? static_cast<int32_t>(xh) : 0;
  }
}

// The pixels [lo, hi] of a tile row are covered by vectors at logical starts lo, lo +
// kLanes, ...; each vector is loaded at min(start, kTile - kLanes) so that it stays in the
// row, and its lanes before the logical start are masked out (no pixel is done twice).
inline int vector_at(int start) { return std::min(start, kTile - kLanes); }

// exp(x) for x in [-20, 1]: Cephes' expf (range reduction and its degree-5 polynomial,
// relative error < 1e-7 over that range, measured against double exp) in plain vector
// arithmetic, so that every lane, pass and instruction set gives the same bits and the
// forward and backward passes agree on each alpha. The polynomial is evaluated in Estrin's
// form: three independent pairs instead of one chain of six multiply-adds (the chain's
// latency, not its arithmetic, bounded the pixel loops).
inline FV exp_poly(FV x) {
  const float shifter = 12582912.0f;  // 1.5 * 2^23: adding it rounds to the nearest integer
  const FV fn = (x * 1.44269504088896341f + shifter) - shifter;
  FV r = x - fn * 0.693359375f;
  r = r - fn * -2.12194440e-4f;
  const FV r2 = r * r;
  const FV p01 = 5.0000001201e-1f + 1.6666665459e-1f * r;
  const FV p23 = 4.1665795894e-2f + 8.3334519073e-3f * r;
  const FV p45 = 1.3981999507e-3f + 1.9875691500e-4f * r;
  const FV q = p01 + r2 * (p23 + r2 * p45);
  const IV bits = (__builtin_convertvector(fn, IV) + 127) << 23;
  FV scale;  // 2^n
  std::memcpy(&scale, &bits, sizeof scale);
  return ((q * r2 + r) + 1.0f) * scale;
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

// kD > 0: the number of feature channels fixed at compile time (loops unrolled); 0: any.
template <int kD>
void forward_channels(const float* features, int channels_in, Binning& b, float* out,
                      int threads) {
  const int channels = kD > 0 ? kD : channels_in;
  const int dp = channels + 1;
  const int64_t tiles = static_cast<int64_t>(b.tile_start.size()) - 1;
  const size_t pixels = static_cast<size_t>(b.cameras) * b.width * b.height;
  b.t_final.assign(pixels, 1.0f);
  b.n_used.assign(pixels, 0);
  const int workers = std::max(1, threads);
  const int64_t visible = static_cast<int64_t>(b.rows.size());
  b.features.resize(static_cast<size_t>(visible * channels));
  const int64_t block = 4096;
  parallel_for((visible + block - 1) / block, workers, [&](int64_t blk, int) {
    for (int64_t i = blk * block; i < std::min(visible, (blk + 1) * block); ++i)
      std::copy(features + int64_t{b.rows[i]} * channels, features + (int64_t{b.rows[i]} + 1) * channels,
                b.features.begin() + i * channels);
  });
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
    int row_alive[kTile] = {};
    for (int r = 0; r < kTile; ++r) {
      for (int col = 0; col < kTile; ++col) {
        const bool in = r < box.h && col < box.w;
        trans[r * kTile + col] = 1.0f;
        alive[r * kTile + col] = in ? -1 : 0;
        row_alive[r] += in;
      }
    }
    for (int col = 0; col < kTile; ++col) cx[col] = static_cast<float>(box.x0 + col) + 0.5f;
    int64_t n_alive = static_cast<int64_t>(box.w) * box.h;
    const int64_t start = b.tile_start[tile], end = b.tile_start[tile + 1];
    for (int64_t k = start; k < std::min(end, start + kPrefetch); ++k) prefetch_entry(b, k, channels);
    for (int64_t k = start; k < end && n_alive > 0; ++k) {
      if (k + kPrefetch < end) prefetch_entry(b, k + kPrefetch, channels);
      const int64_t id = b.ids[k];
      const Splat& p = b.splats[id];
      const float* f = b.features.data() + id * channels;
      const IV rank = splat(static_cast<int32_t>(k - start + 1));
      int r0, r1;
      if (!row_range(p, box.y0, box.h, r0, r1)) continue;
      int32_t span_lo[kTile], span_hi[kTile];
      tile_spans(p, box, r0, r1, span_lo, span_hi);
      for (int r = r0; r <= r1; ++r) {
        const int lo = span_lo[r], hi = span_hi[r];
        if (!row_alive[r] || lo > hi) continue;
        const float yc = static_cast<float>(box.y0 + r) + 0.5f;
        const float dy = p.my - yc;
        const float row_term = -0.5f * p.c * dy * dy;
        for (int cs = lo; cs <= hi; cs += kLanes) {
          const int vs = vector_at(cs);
          const int base = r * kTile + vs;
          const FV raw = raw_alpha(p, p.mx - load(cx + vs), dy, row_term);
          const IV col = lane + vs;
          const IV in = (col >= cs) & (col <= hi) & load(alive + base) & (raw > kAlphaThreshold);
          if (!lane_bits(in)) continue;
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
          if (lane_bits(done)) {
            const int finished = lane_count(done);
            row_alive[r] -= finished;
            n_alive -= finished;
          }
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

template <int kD>
void backward_channels(const float* opacities, int channels_in, const Binning& b,
                       const float* grad_out, float* grad_means2d, float* grad_conics,
                       float* grad_opacities, float* grad_features, float* absgrad_means2d,
                       int threads) {
  const int channels = kD > 0 ? kD : channels_in;
  const int dp = channels + 1;
  const int64_t tiles = static_cast<int64_t>(b.tile_start.size()) - 1;
  const int64_t v = static_cast<int64_t>(b.rows.size());
  const bool want_abs = absgrad_means2d != nullptr;
  // per Gaussian: means 2, conics 3, opacity 1, features, (the means' absolute gradient 2)
  const int64_t stride = 6 + channels + (want_abs ? 2 : 0);
  // Each worker adds into its own array of (rank, stride) gradients (no atomics; one or two
  // cache lines per Gaussian), summed into the outputs by row at the end; fewer workers
  // when those would take more than 1 GiB. Tiles go to workers by a fixed rule, so the sums
  // (float additions in a fixed order) are the same on every run: resume is exact.
  const int64_t per_worker = std::max<int64_t>(1, v * stride * int64_t{sizeof(float)});
  const int workers = static_cast<int>(std::max<int64_t>(
      1, std::min<int64_t>({int64_t{std::max(1, threads)}, tiles, (int64_t{1} << 30) / per_worker})));
  std::vector<std::vector<float>> private_grads(workers);
  private_grads[0].assign(static_cast<size_t>(v * stride), 0.0f);  // the others: when they start
  std::vector<std::vector<float>> scratch(workers);
  std::vector<std::vector<int32_t>> scratch_used(workers);
  const int ran = parallel_for(tiles, workers, [&](int64_t tile, int worker) {
    const TileBox box = tile_box(b, tile);
    const int64_t start = b.tile_start[tile];
    if (b.tile_start[tile + 1] == start) return;
    if (private_grads[worker].empty()) private_grads[worker].assign(static_cast<size_t>(v * stride), 0.0f);
    const IV lane = lane_index();
    std::vector<float>& buf = scratch[worker];
    buf.assign(static_cast<size_t>(kPixels) * (dp + 2) + kTile, 0.0f);
    float* trans = buf.data();          // (pixels) transmittance, walked back towards 1
    float* suffix = trans + kPixels;    // (pixels) sum over later Gaussians of w (g . f)
    float* g = suffix + kPixels;        // (D + 1, pixels) gradient of the output
    float* cx = g + kPixels * dp;       // (kTile) pixel-centre x of the tile's columns
    std::vector<int32_t>& used = scratch_used[worker];
    used.assign(kPixels, 0);
    int32_t row_used[kTile] = {};  // per row: the most list entries a pixel used
    for (int r = 0; r < box.h; ++r) {
      for (int col = 0; col < box.w; ++col) {
        const int px = r * kTile + col;
        const size_t at = (static_cast<size_t>(box.cam) * b.height + box.y0 + r) * b.width + box.x0 + col;
        trans[px] = b.t_final[at];
        used[px] = b.n_used[at];
        row_used[r] = std::max(row_used[r], used[px]);
        for (int d = 0; d < dp; ++d) g[d * kPixels + px] = grad_out[at * dp + d];
      }
    }
    for (int col = 0; col < kTile; ++col) cx[col] = static_cast<float>(box.x0 + col) + 0.5f;
    const int32_t most = *std::max_element(row_used, row_used + kTile);
    float* grads = private_grads[worker].data();
    for (int32_t kk = most - 1; kk >= std::max(0, most - kPrefetch); --kk) prefetch_entry(b, start + kk, channels);
    for (int32_t kk = most - 1; kk >= 0; --kk) {
      if (kk >= kPrefetch) {
        prefetch_entry(b, start + kk - kPrefetch, channels);
#if defined(__GNUC__)
        __builtin_prefetch(grads + b.ids[start + kk - kPrefetch] * stride, 1);
#endif
      }
      const int64_t id = b.ids[start + kk];
      const Splat& p = b.splats[id];
      const float* f = b.features.data() + id * channels;
      int r0, r1;
      if (!row_range(p, box.y0, box.h, r0, r1)) continue;
      const IV rank = splat(kk);
      FV l_mx{}, l_my{}, l_ca{}, l_cb{}, l_cc{}, l_op{};  // per-lane sums of the gradients
      FV l_ax{}, l_ay{};  // per-lane sums of the means' per-pixel |gradient|
      FV l_f[kD > 0 ? kD : kMaxChannels];  // per-lane sums of the feature gradient
      for (int d = 0; d < channels; ++d) l_f[d] = FV{};
      bool touched = false;
      int32_t span_lo[kTile], span_hi[kTile];
      tile_spans(p, box, r0, r1, span_lo, span_hi);
      for (int r = r0; r <= r1; ++r) {
        const int lo = span_lo[r], hi = span_hi[r];
        if (row_used[r] <= kk || lo > hi) continue;
        const float yc = static_cast<float>(box.y0 + r) + 0.5f;
        const float dy = p.my - yc;
        const float row_term = -0.5f * p.c * dy * dy;
        for (int cs = lo; cs <= hi; cs += kLanes) {
          const int vs = vector_at(cs);
          const int base = r * kTile + vs;
          const FV dx = p.mx - load(cx + vs);
          const FV raw = raw_alpha(p, dx, dy, row_term);
          const IV col = lane + vs;
          const IV in = (col >= cs) & (col <= hi) & (rank < load(used.data() + base)) &
                        (raw > kAlphaThreshold);
          if (!lane_bits(in)) continue;
          touched = true;
          FV g_dot_f = load(g + channels * kPixels + base);  // the alpha channel: f = 1
          for (int d = 0; d < channels; ++d) g_dot_f += load(g + d * kPixels + base) * f[d];
          const FV alpha = raw > kMaxAlpha ? splat(kMaxAlpha) : raw;
          const FV inv_one_minus = 1.0f / (1.0f - alpha);
          const FV t_after = load(trans + base);
          const FV t = in ? t_after * inv_one_minus : t_after;  // transmittance before this one
          store(trans + base, t);
          const FV weight = alpha * t;
          const FV later = load(suffix + base);
          // dL/dalpha = T_before (g . f) - (sum over later Gaussians of w (g . f)) / (1 - alpha)
          const FV g_alpha = t * g_dot_f - later * inv_one_minus;
          store(suffix + base, in ? later + weight * g_dot_f : later);
          const FV w = in ? weight : FV{};
          // alpha = o exp(-sigma) where the clamp is not active: dL/d(-sigma) = dL/dalpha alpha
          const FV g_ns = in & (raw < kMaxAlpha) ? g_alpha * alpha : FV{};
          l_op += g_ns;  // divided by the opacity at the end
          const FV g_mx = g_ns * (p.a * dx + p.b * dy);
          const FV g_my = g_ns * (p.b * dx + p.c * dy);
          l_mx -= g_mx;
          l_my -= g_my;
          if (want_abs) {
            l_ax += abs_lanes(g_mx);
            l_ay += abs_lanes(g_my);
          }
          l_ca -= 0.5f * g_ns * dx * dx;
          l_cb -= g_ns * dx * dy;
          l_cc -= 0.5f * g_ns * dy * dy;
          for (int d = 0; d < channels; ++d) l_f[d] += w * load(g + d * kPixels + base);
        }
      }
      if (!touched) continue;
      float* gi = grads + id * stride;  // means 2, conics 3, opacity, features
      gi[0] += lane_sum(l_mx);
      gi[1] += lane_sum(l_my);
      gi[2] += lane_sum(l_ca);
      gi[3] += lane_sum(l_cb);
      gi[4] += lane_sum(l_cc);
      gi[5] += lane_sum(l_op);
      for (int d = 0; d < channels; ++d) gi[6 + d] += lane_sum(l_f[d]);
      if (want_abs) {
        gi[6 + channels] += lane_sum(l_ax);
        gi[7 + channels] += lane_sum(l_ay);
      }
    }
  }, /*fixed=*/true);
  const int64_t block = 4096;
  parallel_for((v + block - 1) / block, workers, [&](int64_t blk, int) {
    for (int64_t i = blk * block; i < std::min(v, (blk + 1) * block); ++i) {
      const int64_t row = b.rows[i];
      for (int w = 0; w < ran; ++w) {
        if (private_grads[w].empty()) continue;
        const float* gi = private_grads[w].data() + i * stride;
        for (int j = 0; j < 2; ++j) grad_means2d[2 * row + j] += gi[j];
        for (int j = 0; j < 3; ++j) grad_conics[3 * row + j] += gi[2 + j];
        grad_opacities[row] += gi[5];
        for (int d = 0; d < channels; ++d) grad_features[row * channels + d] += gi[6 + d];
        if (want_abs)
          for (int j = 0; j < 2; ++j) absgrad_means2d[2 * row + j] += gi[6 + channels + j];
      }
      // dL/do = dL/d(-sigma) / o (alpha = o exp(-sigma))
      grad_opacities[row] /= std::max(opacities[row], 1e-30f);
    }
  });
}

void composite_forward(const float* features, int channels, Binning& b, float* out,
                       int threads) {
  switch (channels) {
    case 3: return forward_channels<3>(features, channels, b, out, threads);
    case 4: return forward_channels<4>(features, channels, b, out, threads);
    default: return forward_channels<0>(features, channels, b, out, threads);
  }
}

void composite_backward(const float* opacities, int channels, const Binning& b,
                        const float* grad_out, float* grad_means2d, float* grad_conics,
                        float* grad_opacities, float* grad_features, float* absgrad_means2d,
                        int threads) {
  switch (channels) {
    case 3:
      return backward_channels<3>(opacities, channels, b, grad_out, grad_means2d, grad_conics,
                                  grad_opacities, grad_features, absgrad_means2d, threads);
    case 4:
      return backward_channels<4>(opacities, channels, b, grad_out, grad_means2d, grad_conics,
                                  grad_opacities, grad_features, absgrad_means2d, threads);
    default:
      return backward_channels<0>(opacities, channels, b, grad_out, grad_means2d, grad_conics,
                                  grad_opacities, grad_features, absgrad_means2d, threads);
  }
}

}  // namespace RS_ISA
}  // namespace rs
