// TensoRF's vector-matrix tables as the compiled modules read them (feature_grids.VMTables'
// row-major layout): where a point's taps fall, their weights, and the layout tuple from
// Python. Shared by the lookup (vm_lookup.cpp) and the marcher (march.cpp). Include after
// Python.h.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

namespace rs {
namespace vm {

constexpr int kModes[3][3] = {{0, 1, 2}, {0, 2, 1}, {1, 2, 0}};

struct Layout {
  int64_t channels;                      // C: components per mode
  int64_t height[3], width[3], plane0[3];  // plane m: rows plane0[m] + y * width[m] + x
  int64_t length[3], line0[3];           // line m: rows line0[m] + i
};

struct Tap1 {
  int64_t i0;
  float f;  // weight of i0 + 1
};

inline Tap1 tap(float u, int64_t n) {
  const float p = (std::min(std::max(u, -1.0f), 1.0f) + 1.0f) * 0.5f * static_cast<float>(n - 1);
  int64_t i0 = static_cast<int64_t>(std::floor(p));
  i0 = std::min<int64_t>(std::max<int64_t>(i0, 0), n - 2);
  return {i0, p - static_cast<float>(i0)};
}

// The six rows and weights a point reads for mode m.
struct Taps {
  int64_t p00, p01, p10, p11, l0, l1;
  float w00, w01, w10, w11, v0, v1;
};

inline Taps taps(const Layout& L, const float* x, int m) {
  const int a = kModes[m][0], b = kModes[m][1], c = kModes[m][2];
  const Tap1 tx = tap(x[a], L.width[m]), ty = tap(x[b], L.height[m]), tl = tap(x[c], L.length[m]);
  Taps t;
  t.p00 = L.plane0[m] + ty.i0 * L.width[m] + tx.i0;
  t.p01 = t.p00 + 1;
  t.p10 = t.p00 + L.width[m];
  t.p11 = t.p10 + 1;
  t.w00 = (1 - tx.f) * (1 - ty.f);
  t.w01 = tx.f * (1 - ty.f);
  t.w10 = (1 - tx.f) * ty.f;
  t.w11 = tx.f * ty.f;
  t.l0 = L.line0[m] + tl.i0;
  t.l1 = t.l0 + 1;
  t.v0 = 1 - tl.f;
  t.v1 = tl.f;
  return t;
}

// The plane's bilinear tap and the line's linear tap of channel r.
inline float plane_tap(const Taps& t, const float* __restrict a, const float* __restrict b,
                       const float* __restrict c, const float* __restrict d, int64_t r) {
  return t.w00 * a[r] + t.w01 * b[r] + t.w10 * c[r] + t.w11 * d[r];
}

inline float line_tap(const Taps& t, const float* __restrict e, const float* __restrict f, int64_t r) {
  return t.v0 * e[r] + t.v1 * f[r];
}

template <class T>
T* ptr(unsigned long long address) {
  return reinterpret_cast<T*>(static_cast<uintptr_t>(address));
}

// layout: (C, h0, w0, h1, w1, h2, w2, n0, n1, n2); every size >= 2 (checked in vm_cpp.py).
inline bool parse_layout(PyObject* tuple, Layout& L, int64_t& plane_rows, int64_t& line_rows) {
  long long v[10];
  if (!PyArg_ParseTuple(tuple, "LLLLLLLLLL", &v[0], &v[1], &v[2], &v[3], &v[4], &v[5], &v[6],
                        &v[7], &v[8], &v[9]))
    return false;
  L.channels = v[0];
  plane_rows = line_rows = 0;
  for (int m = 0; m < 3; ++m) {
    L.height[m] = v[1 + 2 * m];
    L.width[m] = v[2 + 2 * m];
    L.length[m] = v[7 + m];
    if (L.height[m] < 2 || L.width[m] < 2 || L.length[m] < 2 || L.channels < 1) {
      PyErr_SetString(PyExc_ValueError, "vm layout: sizes must be >= 2 and channels >= 1");
      return false;
    }
    L.plane0[m] = plane_rows;
    L.line0[m] = line_rows;
    plane_rows += L.height[m] * L.width[m];
    line_rows += L.length[m];
  }
  return true;
}


}  // namespace vm
}  // namespace rs
