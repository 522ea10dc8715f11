// Python module rainyscape.fields.gaussians._rasterize_cpp: the kernel of kernel.h behind
// the CPython C API only (no torch headers: it builds without torch). Arrays arrive as
// data pointers (Python ints) of contiguous CPU tensors checked by rasterize_cpp.py, which
// keeps them alive; the binning (with the 2D Gaussians it read) lives in a capsule that the
// forward pass completes and the backward pass reads.
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <cstdint>
#include <exception>
#include <new>
#include <stdexcept>
#include <string>

#include "kernel.h"
#include "py_release.h"

using rs::run_released;

namespace {

const char* kCapsule = "rainyscape.gaussians.binning";

void free_binning(PyObject* capsule) {
  delete static_cast<rs::Binning*>(PyCapsule_GetPointer(capsule, kCapsule));
}

rs::Binning* binning_of(PyObject* capsule) {
  return static_cast<rs::Binning*>(PyCapsule_GetPointer(capsule, kCapsule));
}

template <class T>
T* ptr(unsigned long long address) {
  return reinterpret_cast<T*>(static_cast<uintptr_t>(address));
}

PyObject* py_bin(PyObject*, PyObject* args) {
  unsigned long long means2d, conics, opacities, radii, depths;
  long long cameras, gaussians;
  int width, height, threads;
  if (!PyArg_ParseTuple(args, "KKKKKLLiii", &means2d, &conics, &opacities, &radii, &depths,
                        &cameras, &gaussians, &width, &height, &threads))
    return nullptr;
  if (cameras < 0 || gaussians < 0 || width < 0 || height < 0) {
    PyErr_SetString(PyExc_ValueError, "negative size");
    return nullptr;
  }
  auto* b = new (std::nothrow) rs::Binning();
  if (!b) return PyErr_NoMemory();
  rs::Splats s;
  s.means2d = ptr<const float>(means2d);
  s.conics = ptr<const float>(conics);
  s.opacities = ptr<const float>(opacities);
  s.radii = ptr<const int32_t>(radii);
  s.cameras = cameras;
  s.gaussians = gaussians;
  s.width = width;
  s.height = height;
  if (!run_released([&] { rs::bin_splats(s, ptr<const float>(depths), threads, *b); })) {
    delete b;
    return nullptr;
  }
  PyObject* capsule = PyCapsule_New(b, kCapsule, free_binning);
  if (!capsule) delete b;
  return capsule;
}

PyObject* py_pairs(PyObject*, PyObject* args) {
  PyObject* capsule;
  if (!PyArg_ParseTuple(args, "O", &capsule)) return nullptr;
  rs::Binning* b = binning_of(capsule);
  if (!b) return nullptr;
  return PyLong_FromSize_t(b->ids.size());
}

PyObject* py_forward(PyObject*, PyObject* args) {
  PyObject* capsule;
  unsigned long long features, out;
  int channels, threads;
  if (!PyArg_ParseTuple(args, "OKiKi", &capsule, &features, &channels, &out, &threads))
    return nullptr;
  rs::Binning* b = binning_of(capsule);
  if (!b) return nullptr;
  if (channels < 0 || channels > rs::kMaxChannels) {
    PyErr_Format(PyExc_ValueError, "the kernel composites 0 to %d feature channels", rs::kMaxChannels);
    return nullptr;
  }
  if (!run_released([&] {
        rs::composite_forward(ptr<const float>(features), channels, *b, ptr<float>(out), threads);
      }))
    return nullptr;
  Py_RETURN_NONE;
}

PyObject* py_backward(PyObject*, PyObject* args) {
  PyObject* capsule;
  unsigned long long opacities, grad_out, g_means2d, g_conics, g_opacities, g_features,
      absgrad_means2d;  // 0: not wanted
  int channels, threads;
  if (!PyArg_ParseTuple(args, "OKiKKKKKKi", &capsule, &opacities, &channels, &grad_out,
                        &g_means2d, &g_conics, &g_opacities, &g_features, &absgrad_means2d,
                        &threads))
    return nullptr;
  rs::Binning* b = binning_of(capsule);
  if (!b) return nullptr;
  if (b->t_final.size() != static_cast<size_t>(b->cameras) * b->width * b->height ||
      b->features.size() != b->rows.size() * static_cast<size_t>(channels)) {
    PyErr_SetString(PyExc_RuntimeError, "backward before forward on this binning");
    return nullptr;
  }
  if (!run_released([&] {
        rs::composite_backward(ptr<const float>(opacities), channels, *b,
                               ptr<const float>(grad_out), ptr<float>(g_means2d),
                               ptr<float>(g_conics), ptr<float>(g_opacities),
                               ptr<float>(g_features), ptr<float>(absgrad_means2d), threads);
      }))
    return nullptr;
  Py_RETURN_NONE;
}

// The views tuple: (viewmats, Ks, offsets, C, width, height, window_width, window_height,
// near_plane, far_plane, eps2d), pointers as ints.
#define VIEWS_FORMAT "(KKKLiiiifff)"
#define VIEWS_ARGS(v) &viewmats, &intrinsics, &offsets, &cameras, &v.width, &v.height, \
    &v.window_width, &v.window_height, &v.near_plane, &v.far_plane, &v.eps2d

void set_views(rs::Views& v, unsigned long long viewmats, unsigned long long intrinsics,
               unsigned long long offsets, long long cameras) {
  v.viewmats = ptr<const float>(viewmats);
  v.intrinsics = ptr<const float>(intrinsics);
  v.offsets = ptr<const float>(offsets);
  v.cameras = cameras;
}

PyObject* py_project(PyObject*, PyObject* args) {
  unsigned long long means, quats, scales, opacities, means2d, conics, depths, radii;
  unsigned long long viewmats, intrinsics, offsets;
  long long n, cameras;
  int threads;
  rs::Views v;
  if (!PyArg_ParseTuple(args, "KKKKL" VIEWS_FORMAT "KKKKi", &means, &quats, &scales,
                        &opacities, &n, VIEWS_ARGS(v), &means2d, &conics, &depths, &radii,
                        &threads))
    return nullptr;
  set_views(v, viewmats, intrinsics, offsets, cameras);
  if (!run_released([&] {
        rs::project_forward(ptr<const float>(means), ptr<const float>(quats),
                            ptr<const float>(scales), ptr<const float>(opacities), n, v,
                            ptr<float>(means2d), ptr<float>(conics), ptr<float>(depths),
                            ptr<int32_t>(radii), threads);
      }))
    return nullptr;
  Py_RETURN_NONE;
}

PyObject* py_project_backward(PyObject*, PyObject* args) {
  unsigned long long means, quats, scales, g_means2d, g_conics, g_depths, g_means, g_quats,
      g_scales;
  unsigned long long viewmats, intrinsics, offsets;
  long long n, cameras;
  int threads;
  rs::Views v;
  if (!PyArg_ParseTuple(args, "KKKL" VIEWS_FORMAT "KKKKKKi", &means, &quats, &scales, &n,
                        VIEWS_ARGS(v), &g_means2d, &g_conics, &g_depths, &g_means, &g_quats,
                        &g_scales, &threads))
    return nullptr;
  set_views(v, viewmats, intrinsics, offsets, cameras);
  if (!run_released([&] {
        rs::project_backward(ptr<const float>(means), ptr<const float>(quats),
                             ptr<const float>(scales), n, v, ptr<const float>(g_means2d),
                             ptr<const float>(g_conics), ptr<const float>(g_depths),
                             ptr<float>(g_means), ptr<float>(g_quats), ptr<float>(g_scales),
                             threads);
      }))
    return nullptr;
  Py_RETURN_NONE;
}

PyObject* py_simd(PyObject*, PyObject*) { return PyUnicode_FromString(rs::simd_name()); }

PyMethodDef kMethods[] = {
    {"project", py_project, METH_VARARGS,
     "project(means, quats, scales, opacities, N, views, means2d, conics, depths, radii,"
     " threads): EWA projection into the given outputs"},
    {"project_backward", py_project_backward, METH_VARARGS,
     "project_backward(means, quats, scales, N, views, grad_means2d, grad_conics,"
     " grad_depths, grad_means, grad_quats, grad_scales, threads): adds into the gradients"},
    {"bin", py_bin, METH_VARARGS,
     "bin(means2d, conics, opacities, radii, depths, C, N, width, height, threads)"
     " -> binning: depth-sorted Gaussian lists of every 16 x 16 tile"},
    {"pairs", py_pairs, METH_VARARGS, "pairs(binning) -> number of Gaussian-tile pairs"},
    {"simd", py_simd, METH_NOARGS, "simd() -> the build of the compositing that runs here"},
    {"forward", py_forward, METH_VARARGS,
     "forward(binning, features, D, out, threads): out (C, H, W, D + 1)"},
    {"backward", py_backward, METH_VARARGS,
     "backward(binning, opacities, D, grad_out, grad_means2d, grad_conics,"
     " grad_opacities, grad_features, absgrad_means2d, threads): adds into the (zero)"
     " gradients; absgrad_means2d 0: not wanted"},
    {nullptr, nullptr, 0, nullptr}};

PyModuleDef kModule = {PyModuleDef_HEAD_INIT, "_rasterize_cpp",
                       "Compiled CPU rasteriser of projected Gaussians (see rasterize_cpp.py).",
                       -1, kMethods, nullptr, nullptr, nullptr, nullptr};

}  // namespace

PyMODINIT_FUNC PyInit__rasterize_cpp(void) { return PyModule_Create(&kModule); }
