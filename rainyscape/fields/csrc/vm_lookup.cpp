// Python module rainyscape.fields._vm_cpp: TensoRF's vector-matrix lookup on row-major tables
// (feature_grids.VMTables' layout), forward and backward, in C++. CPython C API only (no torch
// headers); arrays arrive as data pointers of contiguous float32 CPU tensors checked by
// vm_cpp.py, which keeps them alive.
//
// Feature r of mode m at a point is plane_m(a, b)[r] * line_m(c)[r] for the axis triples
// (x, y | z), (x, z | y), (y, z | x); bilinear and linear taps with aligned corners and
// coordinates clamped to [-1, 1], as feature_grids.bilinear_taps / linear_taps. Output rows
// are (3 C) long, mode-major. Why C++: torch's grid_sample reads channel-major planes (one
// cache miss per channel and tap) and its backward, like embedding_bag's, runs through
// generic scatter code; here a tap is one contiguous row of C floats.
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include "parallel.h"
#include "vm_taps.h"
#include "py_release.h"

namespace {

using namespace rs::vm;
constexpr int64_t kBlock = 2048;  // points per work item

// The per-channel loops, each over pointers that cannot overlap (distinct table rows, or a
// row and a local buffer): written apart with __restrict so the compiler vectorises them,
// which it would not do for one loop writing six rows it must assume may alias.
constexpr int64_t kChunk = 64;  // channels per pass of the backward's local buffers

inline void mode_forward(const Taps& t, const float* __restrict a, const float* __restrict b,
                         const float* __restrict c, const float* __restrict d,
                         const float* __restrict e, const float* __restrict f,
                         float* __restrict o, int64_t n) {
  for (int64_t r = 0; r < n; ++r) o[r] = plane_tap(t, a, b, c, d, r) * line_tap(t, e, f, r);
}

// d out / d plane tap (before its weight) and d out / d line tap, for n channels.
inline void mode_partials(const Taps& t, const float* __restrict a, const float* __restrict b,
                          const float* __restrict c, const float* __restrict d,
                          const float* __restrict e, const float* __restrict f,
                          const float* __restrict g, float* __restrict gpl,
                          float* __restrict gln, int64_t n) {
  for (int64_t r = 0; r < n; ++r) {
    gpl[r] = g[r] * line_tap(t, e, f, r);
    gln[r] = g[r] * plane_tap(t, a, b, c, d, r);
  }
}

inline void axpy(float* __restrict y, const float* __restrict x, float w, int64_t n) {
  for (int64_t r = 0; r < n; ++r) y[r] += w * x[r];
}

void forward(const Layout& L, const float* plane, const float* line, const float* points,
             int64_t n, float* out, int threads) {
  const int64_t C = L.channels;
  const int64_t blocks = (n + kBlock - 1) / kBlock;
  rs::detail::parallel_for(blocks, threads, [&](int64_t block, int) {
    const int64_t end = std::min(n, (block + 1) * kBlock);
    for (int64_t i = block * kBlock; i < end; ++i) {
      for (int m = 0; m < 3; ++m) {
        const Taps t = taps(L, points + 3 * i, m);
        const float *a = plane + t.p00 * C, *b = plane + t.p01 * C, *c = plane + t.p10 * C,
                    *d = plane + t.p11 * C, *e = line + t.l0 * C, *f = line + t.l1 * C;
        mode_forward(t, a, b, c, d, e, f, out + (3 * i + m) * C, C);
      }
    }
  });
}

// Adds into grad_plane / grad_line. Worker w accumulates blocks w, w + threads, ... into its
// own buffer (worker 0 straight into the outputs), summed in worker order: the same sums in
// the same order on every run, so resumed runs match uninterrupted ones.
void backward(const Layout& L, const float* plane, const float* line, const float* points,
              int64_t n, const float* grad_out, float* grad_plane, float* grad_line,
              int64_t plane_rows, int64_t line_rows, int threads) {
  const int64_t C = L.channels;
  const int64_t blocks = (n + kBlock - 1) / kBlock;
  threads = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(threads, blocks)));
  std::vector<std::vector<float>> planes(threads - 1), lines(threads - 1);
  for (int w = 1; w < threads; ++w) {
    planes[w - 1].assign(plane_rows * C, 0.0f);
    lines[w - 1].assign(line_rows * C, 0.0f);
  }
  rs::detail::parallel_for(blocks, threads, [&](int64_t block, int worker) {
    float* gp = worker == 0 ? grad_plane : planes[worker - 1].data();
    float* gl = worker == 0 ? grad_line : lines[worker - 1].data();
    const int64_t end = std::min(n, (block + 1) * kBlock);
    for (int64_t i = block * kBlock; i < end; ++i) {
      for (int m = 0; m < 3; ++m) {
        const Taps t = taps(L, points + 3 * i, m);
        const float *a = plane + t.p00 * C, *b = plane + t.p01 * C, *c = plane + t.p10 * C,
                    *d = plane + t.p11 * C, *e = line + t.l0 * C, *f = line + t.l1 * C;
        float *ga = gp + t.p00 * C, *gb = gp + t.p01 * C, *gc = gp + t.p10 * C,
              *gd = gp + t.p11 * C, *ge = gl + t.l0 * C, *gf = gl + t.l1 * C;
        const float* g = grad_out + (3 * i + m) * C;
        for (int64_t r0 = 0; r0 < C; r0 += kChunk) {
          const int64_t k = std::min(kChunk, C - r0);
          float gpl[kChunk], gln[kChunk];
          mode_partials(t, a + r0, b + r0, c + r0, d + r0, e + r0, f + r0, g + r0, gpl, gln, k);
          axpy(ga + r0, gpl, t.w00, k);
          axpy(gb + r0, gpl, t.w01, k);
          axpy(gc + r0, gpl, t.w10, k);
          axpy(gd + r0, gpl, t.w11, k);
          axpy(ge + r0, gln, t.v0, k);
          axpy(gf + r0, gln, t.v1, k);
        }
      }
    }
  }, /*fixed=*/true);
  for (int w = 1; w < threads; ++w) {
    const float* sp = planes[w - 1].data();
    for (int64_t k = 0; k < plane_rows * C; ++k) grad_plane[k] += sp[k];
    const float* sl = lines[w - 1].data();
    for (int64_t k = 0; k < line_rows * C; ++k) grad_line[k] += sl[k];
  }
}

PyObject* py_forward(PyObject*, PyObject* args) {
  PyObject* layout;
  unsigned long long plane, line, points, out;
  long long n;
  int threads;
  if (!PyArg_ParseTuple(args, "O!KKKLKi", &PyTuple_Type, &layout, &plane, &line, &points, &n,
                        &out, &threads))
    return nullptr;
  Layout L;
  int64_t plane_rows, line_rows;
  if (!parse_layout(layout, L, plane_rows, line_rows)) return nullptr;
  if (!rs::run_released([&] {
        forward(L, ptr<const float>(plane), ptr<const float>(line), ptr<const float>(points), n,
                ptr<float>(out), threads);
      }))
    return nullptr;
  Py_RETURN_NONE;
}

PyObject* py_backward(PyObject*, PyObject* args) {
  PyObject* layout;
  unsigned long long plane, line, points, grad_out, grad_plane, grad_line;
  long long n;
  int threads;
  if (!PyArg_ParseTuple(args, "O!KKKLKKKi", &PyTuple_Type, &layout, &plane, &line, &points, &n,
                        &grad_out, &grad_plane, &grad_line, &threads))
    return nullptr;
  Layout L;
  int64_t plane_rows, line_rows;
  if (!parse_layout(layout, L, plane_rows, line_rows)) return nullptr;
  if (!rs::run_released([&] {
        backward(L, ptr<const float>(plane), ptr<const float>(line), ptr<const float>(points), n,
                 ptr<const float>(grad_out), ptr<float>(grad_plane), ptr<float>(grad_line),
                 plane_rows, line_rows, threads);
      }))
    return nullptr;
  Py_RETURN_NONE;
}

PyMethodDef kMethods[] = {
    {"forward", py_forward, METH_VARARGS,
     "forward(layout, plane, line, points, N, out, threads): out (N, 3 C)"},
    {"backward", py_backward, METH_VARARGS,
     "backward(layout, plane, line, points, N, grad_out, grad_plane, grad_line, threads):"
     " adds into the gradients"},
    {nullptr, nullptr, 0, nullptr}};

PyModuleDef kModule = {PyModuleDef_HEAD_INIT, "_vm_cpp",
                       "Compiled vector-matrix lookup of the grid field (see vm_cpp.py).", -1,
                       kMethods, nullptr, nullptr, nullptr, nullptr};

}  // namespace

PyMODINIT_FUNC PyInit__vm_cpp(void) { return PyModule_Create(&kModule); }
