// Python module rainyscape.fields._march_cpp: the grid field's first pass in C++. For each ray
// it lays out the samples GridField._samples lays out (the linear part in voxel steps, then
// the far part or the one end sample), keeps those whose cell the occupancy grid marks, and
// marches them front to back through the vector-matrix density until the light left falls to
// the threshold. It returns only the samples light still reaches: a packed list (ray, t,
// interval length, grid point, density, rank among the ray's real samples), which is all the render
// with gradients needs. The same arithmetic, in the same order, as the dense torch path
// (grid.py, GridField._march_dense), so both keep the same samples up to float rounding of
// the density sums. Why C++: the dense path spends most of a step's bookkeeping on (rays x
// slots) tensors of which a sixth are live. CPython C API only; arrays arrive as data
// pointers of contiguous CPU tensors checked by grid_march.py, which keeps them alive.
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include "parallel.h"
#include "py_release.h"
#include "vm_taps.h"

namespace {

using namespace rs::vm;
constexpr int64_t kRayBlock = 64;  // rays per work item

struct Settings {
  int64_t n_lin, n_end;  // linear slots (the longest ray's), end slots (far part, or 1)
  bool contract;
  float inner;
  float last_delta;  // the last interval, per unit of ray length (FAR_DELTA, or 0)
  bool force_last;   // the last sample stays live (it takes the light that is left)
  int64_t occ_res;
  float density_scale, density_shift, threshold;
};

struct Rays {
  const float *origins, *directions, *t_a, *t_b, *t_far, *step, *jitter, *length;
};

struct Out {  // one work item's samples, in ray order
  std::vector<int64_t> ray;
  std::vector<float> t, delta, g, sigma;
  std::vector<int32_t> rank;
  int64_t evaluated = 0;
};

inline float softplus(float x) { return x > 20.0f ? x : std::log1p(std::exp(x)); }  // torch's

inline float density(const Layout& L, const float* plane, const float* line, const float* g,
                     const Settings& S) {
  const int64_t C = L.channels;
  float raw = 0.0f;
  for (int m = 0; m < 3; ++m) {
    const Taps t = taps(L, g, m);
    const float *a = plane + t.p00 * C, *b = plane + t.p01 * C, *c = plane + t.p10 * C,
                *d = plane + t.p11 * C, *e = line + t.l0 * C, *f = line + t.l1 * C;
    for (int64_t r = 0; r < C; ++r) raw += plane_tap(t, a, b, c, d, r) * line_tap(t, e, f, r);
  }
  return S.density_scale * softplus(raw + S.density_shift);
}

// Sampling-space point -> grid coordinates (space.contract_to_cube's order of operations).
inline void to_grid(const float* q, const Settings& S, float* g) {
  if (!S.contract) {
    g[0] = q[0], g[1] = q[1], g[2] = q[2];
    return;
  }
  const float r = std::max(std::max(std::fabs(q[0]), std::fabs(q[1])), std::max(std::fabs(q[2]), 1e-9f));
  for (int k = 0; k < 3; ++k)
    g[k] = r <= 1.0f ? S.inner * q[k] : (S.inner + (1.0f - S.inner) * (1.0f - 1.0f / r)) * q[k] / r;
}

inline bool occupied(const uint8_t* occ, const float* g, int64_t res) {  // occupancy.lookup(2 g)
  int64_t idx[3];
  for (int k = 0; k < 3; ++k) {
    const float c = (2.0f * g[k] + 2.0f) * (static_cast<float>(res) / 4.0f);
    idx[k] = std::min<int64_t>(std::max<int64_t>(static_cast<int64_t>(c), 0), res - 1);
  }
  return occ[(idx[0] * res + idx[1]) * res + idx[2]] != 0;
}

void march_ray(int64_t i, const Rays& R, const Settings& S, const Layout& L, const float* plane,
               const float* line, const uint8_t* occ, std::vector<float>& ts, Out& out) {
  const float *o = R.origins + 3 * i, *d = R.directions + 3 * i;
  const float t_a = R.t_a[i], t_b = R.t_b[i], step = R.step[i], jitter = R.jitter[i];
  // The ray's real samples in order: the linear ones before t_b, then the end ones (padding
  // slots in between have zero length and are never live: skipped).
  ts.clear();
  for (int64_t k = 0; k < S.n_lin; ++k) {
    const float t = t_a + (static_cast<float>(k) + jitter) * step;
    if (!(t < t_b)) break;  // t grows with k
    ts.push_back(t);
  }
  if (S.contract) {
    const float t_far = R.t_far[i];
    for (int64_t j = 0; j < S.n_end; ++j) {
      const float u = (static_cast<float>(j) + jitter) / static_cast<float>(S.n_end);
      ts.push_back(1.0f / ((1.0f - u) / t_b + u / t_far));
    }
  } else {
    ts.push_back(t_b);
  }
  const int64_t n = static_cast<int64_t>(ts.size());
  const float length = R.length[i];
  float before = 0.0f;  // optical depth in front of the sample
  for (int64_t s = 0; s < n; ++s) {
    const bool last = s == n - 1;
    const float delta = std::max(0.0f, (last ? S.last_delta : ts[s + 1] - ts[s]) * length);
    float q[3], g[3];
    for (int k = 0; k < 3; ++k) q[k] = o[k] + ts[s] * d[k];
    to_grid(q, S, g);
    if (!((last && S.force_last) || occupied(occ, g, S.occ_res))) continue;
    if (!(std::exp(-before) > S.threshold)) break;  // opaque: nothing behind gets light
    const float sigma = density(L, plane, line, g, S);
    ++out.evaluated;
    out.ray.push_back(i);
    out.t.push_back(ts[s]);
    out.delta.push_back(delta);
    out.g.insert(out.g.end(), g, g + 3);
    out.sigma.push_back(sigma);
    out.rank.push_back(static_cast<int32_t>(s));
    before += sigma * delta;
  }
}

template <class T>
PyObject* to_bytearray(const std::vector<Out>& parts, std::vector<T> Out::*field) {
  size_t n = 0;
  for (const Out& p : parts) n += (p.*field).size();
  PyObject* buf = PyByteArray_FromStringAndSize(nullptr, static_cast<Py_ssize_t>(n * sizeof(T)));
  if (!buf) return nullptr;
  char* dst = PyByteArray_AsString(buf);
  for (const Out& p : parts) {
    const size_t bytes = (p.*field).size() * sizeof(T);
    if (bytes) std::memcpy(dst, (p.*field).data(), bytes);
    dst += bytes;
  }
  return buf;
}

PyObject* py_march(PyObject*, PyObject* args) {
  PyObject* layout;
  unsigned long long plane, line, occ, origins, directions, t_a, t_b, t_far, step, jitter, length;
  long long n_rays, n_lin, n_end, occ_res;
  int contract, force_last, threads;
  float inner, last_delta, scale, shift, threshold;
  if (!PyArg_ParseTuple(args, "O!KKKLKKKKKKKKLLLpfpffffi", &PyTuple_Type, &layout, &plane, &line,
                        &occ, &occ_res, &origins, &directions, &t_a, &t_b, &t_far, &step, &jitter,
                        &length, &n_rays, &n_lin, &n_end, &contract, &inner, &force_last,
                        &last_delta, &scale, &shift, &threshold, &threads))
    return nullptr;
  Layout L;
  int64_t plane_rows, line_rows;
  if (!parse_layout(layout, L, plane_rows, line_rows)) return nullptr;
  if (occ_res < 1 || n_lin < 1 || n_end < 1) {
    PyErr_SetString(PyExc_ValueError, "march: occupancy resolution and slot counts must be >= 1");
    return nullptr;
  }
  const Settings S{n_lin, n_end, contract != 0, inner, last_delta, force_last != 0, occ_res,
                   scale, shift, threshold};
  const Rays R{ptr<const float>(origins), ptr<const float>(directions), ptr<const float>(t_a),
               ptr<const float>(t_b), ptr<const float>(t_far), ptr<const float>(step),
               ptr<const float>(jitter), ptr<const float>(length)};
  const int64_t blocks = (n_rays + kRayBlock - 1) / kRayBlock;
  std::vector<Out> parts(static_cast<size_t>(blocks));
  if (!rs::run_released([&] {
        rs::detail::parallel_for(blocks, threads, [&](int64_t b, int) {
          std::vector<float> ts;
          const int64_t end = std::min<int64_t>(n_rays, (b + 1) * kRayBlock);
          for (int64_t i = b * kRayBlock; i < end; ++i)
            march_ray(i, R, S, L, ptr<const float>(plane), ptr<const float>(line),
                      ptr<const uint8_t>(occ), ts, parts[b]);
        });
      }))
    return nullptr;
  int64_t evaluated = 0;
  for (const Out& p : parts) evaluated += p.evaluated;
  PyObject* items[6] = {to_bytearray(parts, &Out::ray), to_bytearray(parts, &Out::t),
                        to_bytearray(parts, &Out::delta), to_bytearray(parts, &Out::g),
                        to_bytearray(parts, &Out::sigma), to_bytearray(parts, &Out::rank)};
  for (PyObject* item : items) {
    if (!item) {
      for (PyObject* other : items) Py_XDECREF(other);
      return nullptr;
    }
  }
  return Py_BuildValue("(NNNNNNL)", items[0], items[1], items[2], items[3], items[4], items[5],
                       static_cast<long long>(evaluated));
}

PyMethodDef kMethods[] = {
    {"march", py_march, METH_VARARGS,
     "march(layout, plane, line, occupancy, occupancy_res, origins, directions, t_a, t_b, t_far,"
     " step, jitter, length, R, n_lin, n_end, contract, inner, force_last, last_delta,"
     " density_scale, density_shift, threshold, threads) -> (ray, t, delta, g, sigma,"
     " rank as bytearrays, evaluated)"},
    {nullptr, nullptr, 0, nullptr}};

PyModuleDef kModule = {PyModuleDef_HEAD_INIT, "_march_cpp",
                       "Compiled first pass of the grid field (see grid_march.py).", -1, kMethods,
                       nullptr, nullptr, nullptr, nullptr};

}  // namespace

PyMODINIT_FUNC PyInit__march_cpp(void) { return PyModule_Create(&kModule); }
