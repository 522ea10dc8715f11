"""Build of the compiled parts: the CPU rasteriser of the Gaussians, the grid field's
vector-matrix lookup and its first pass (C++17, std::thread, CPython C API only, so no torch
is needed to build them). Package metadata lives in pyproject.toml.

The extensions are optional: without a working C++ compiler the install still succeeds (with
a warning from setuptools) and the torch code is used; tests/test_rasterize_cpp.py,
tests/test_vm_cpp.py and tests/test_grid_march.py fail when a compiler is present but an
extension did not build.
"""

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

CSRC = "rainyscape/fields/gaussians/csrc"
FIELDS = "rainyscape/fields/csrc"
SHARED = "rainyscape/csrc"  # the worker pool and Python glue all modules use


class BuildExt(build_ext):
    """Compiler flags per compiler family. No -march=native (the build may be copied to
    another machine: the kernel picks its AVX2 code at run time); no fast-math and no FMA
    contraction: the forward and backward passes must compute each alpha bit-identically
    to agree on which Gaussians contributed."""

    def build_extensions(self):
        if self.compiler.compiler_type == "msvc":
            args, link = ["/O2", "/std:c++17", "/fp:precise"], []
        else:
            args = ["-O3", "-std=c++17", "-ffp-contract=off", "-fno-math-errno", "-pthread"]
            link = ["-pthread"]
        for ext in self.extensions:
            ext.extra_compile_args = args
            ext.extra_link_args = link
        super().build_extensions()


def extension(name: str, sources: list[str], depends: list[str]) -> Extension:
    """An optional C++ module (the install goes on without it) that includes the shared
    worker pool and Python glue."""
    return Extension(name, sources=sources, depends=depends + [f"{SHARED}/parallel.h", f"{SHARED}/py_release.h"],
                     include_dirs=[SHARED], language="c++", optional=True)


setup(
    ext_modules=[
        extension("rainyscape.fields.gaussians._rasterize_cpp",
                  [f"{CSRC}/module.cpp", f"{CSRC}/kernel.cpp", f"{CSRC}/projection.cpp"],
                  [f"{CSRC}/kernel.h", f"{CSRC}/kernel_common.h", f"{CSRC}/composite_impl.h"]),
        extension("rainyscape.fields._vm_cpp", [f"{FIELDS}/vm_lookup.cpp"], [f"{FIELDS}/vm_taps.h"]),
        extension("rainyscape.fields._march_cpp", [f"{FIELDS}/march.cpp"], [f"{FIELDS}/vm_taps.h"]),
    ],
    cmdclass={"build_ext": BuildExt},
)
