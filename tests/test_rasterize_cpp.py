"""The compiled CPU rasteriser (field.backend=cpp) against the torch rasteriser, in float32:
images, alpha, depth, radii, 2D means and every gradient (means, quaternions, scales,
opacities, colours or SH coefficients, and the 2D means' gradient that densification
reads), on small scenes with several cameras, windows, empty views, Gaussians behind the
cameras, huge Gaussians and opaque stacks that stop early; and that the extension was built
wherever a C++ compiler is present (a silent build failure would quietly fall back to torch).
"""

from __future__ import annotations

import math
import shutil

import pytest
import torch

from rainyscape.cameras import Window
from rainyscape.errors import ConfigError
from rainyscape.fields.gaussians import rasterize as rasterize_module
from rainyscape.fields.gaussians import rasterize_cpp
from rainyscape.fields.gaussians.projection import project_gaussians
from rainyscape.fields.gaussians.rasterize import rasterize, resolve_backend
from rainyscape.fields.gaussians.rasterize_cpp import (binning_pairs, cpp_available,
                                                      project_cpp, unavailable_reason)
from rainyscape.fields.gaussians.rasterize_torch import bin_gaussians

W, H = 45, 37  # not multiples of the 16-pixel tile

needs_cpp = pytest.mark.skipif(not cpp_available(), reason=unavailable_reason() or "built")


def test_extension_is_built_where_a_compiler_is():
    if not (shutil.which("g++") or shutil.which("c++")):
        pytest.skip("no C++ compiler here: the torch rasteriser is the CPU path")
    assert cpp_available(), (f"{unavailable_reason()}: a C++ compiler is present, so "
                             "'pip install -e .' should have built it (see its output)")
    assert rasterize_cpp.simd()


def scene(n: int, seed: int, *, opaque: bool = False, huge: int = 0, behind: int = 0,
          cameras: int = 3):
    """Gaussians in a slab 4 units in front of camera 0; cameras 1 and 2 are turned and
    shifted (some Gaussians leave their view). ``huge``: that many Gaussians larger than the
    view; ``behind``: that many behind camera 0."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([2.5, 2.0, 1.0])
    means[:, 2] += 4.0
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.2 + 0.03
    lo, span = (0.9, 0.099) if opaque else (0.05, 0.9)
    opacities = torch.rand(n, generator=g) * span + lo
    colors = torch.rand(n, 3, generator=g)
    if huge:
        scales[:huge] = torch.rand(huge, 3, generator=g) * 1.5 + 1.5
        opacities[:huge] = torch.rand(huge, generator=g) * 0.45 + 0.05
    if behind:
        means[huge:huge + behind, 2] = -means[huge:huge + behind, 2]
    viewmats = torch.eye(4).repeat(cameras, 1, 1)
    for i in range(1, cameras):
        a = 0.12 * i
        viewmats[i, :3, :3] = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0],
                                            [-math.sin(a), 0, math.cos(a)]])
        viewmats[i, :3, 3] = torch.tensor([0.2 * i, -0.1, 0.3 * i])
    ks = torch.tensor([[55.0, 0, 22.5], [0, 52.0, 18.0], [0, 0, 1]]).repeat(cameras, 1, 1)
    return [means, quats, scales, opacities, colors], viewmats, ks


def render(params, viewmats, ks, backend, window=None, sh_degree=None, seed=0):
    """One render and the gradients of a loss on rgb, alpha and depth: (output, grads)."""
    leaves = [p.detach().clone().requires_grad_(True) for p in params]
    out = rasterize(*leaves, viewmats, ks, W, H, window, sh_degree=sh_degree, backend=backend)
    out.means2d.retain_grad()
    g = torch.Generator().manual_seed(seed)
    w_rgb = torch.randn(out.rgb.shape, generator=g)
    w_alpha = torch.randn(out.alpha.shape, generator=g)
    w_depth = torch.randn(out.depth.shape, generator=g)
    loss = (out.rgb * w_rgb).sum() + (out.alpha * w_alpha).sum()
    (loss + (out.depth * out.alpha * w_depth).sum()).backward()
    return out, [p.grad for p in leaves]


def assert_close_grad(mine, ref, name, rel=2e-4):
    """Gradients agree to ``rel`` of their largest entry (float32 sums in other orders)."""
    scale = float(ref.abs().max())
    err = float((mine - ref).abs().max())
    assert err <= rel * scale + 1e-7, f"{name}: max error {err:.3g} of max {scale:.3g}"


def assert_parity(params, viewmats, ks, window=None, sh_degree=None):
    """The cpp backend equals the torch backend: images, radii, 2D means, all gradients."""
    a, grads_a = render(params, viewmats, ks, "torch", window, sh_degree)
    b, grads_b = render(params, viewmats, ks, "cpp", window, sh_degree)
    assert torch.allclose(b.rgb, a.rgb, atol=2e-5), float((b.rgb - a.rgb).abs().max())
    assert torch.allclose(b.alpha, a.alpha, atol=2e-5)
    assert torch.allclose(b.depth * b.alpha, a.depth * a.alpha, atol=1e-4)
    assert torch.equal(b.radii, a.radii)
    seen = (a.radii > 0).all(-1)
    assert torch.allclose(b.means2d[seen], a.means2d[seen], atol=1e-4)
    assert b.means2d.grad.shape == a.means2d.grad.shape
    assert_close_grad(b.means2d.grad, a.means2d.grad, "means2d")
    names = ("means", "quats", "scales", "opacities", "colors")
    for name, mine, ref in zip(names, grads_b, grads_a):
        assert_close_grad(mine, ref, name)
    return a


@needs_cpp
def test_parity_several_cameras():
    params, viewmats, ks = scene(300, seed=1)
    out = assert_parity(params, viewmats, ks)
    assert (out.alpha > 0.5).float().mean() > 0.3  # the views are covered
    assert ((out.radii > 0).all(-1).sum(1) < 300).any()  # and some Gaussians leave a view


@needs_cpp
def test_parity_opaque_stack_stops_early():
    params, viewmats, ks = scene(300, seed=2, opaque=True)
    out = assert_parity(params, viewmats, ks)
    assert (out.alpha > 0.999).float().mean() > 0.1  # deep stacks: compositing stopped


@needs_cpp
def test_parity_huge_gaussians_and_gaussians_behind():
    params, viewmats, ks = scene(200, seed=3, huge=12, behind=20)
    out = assert_parity(params, viewmats, ks)
    assert (out.radii[0, :12] > 2 * W).any()  # larger than the view
    assert (out.radii[0, 12:32] == 0).all()  # behind camera 0


@needs_cpp
def test_parity_windows():
    params, viewmats, ks = scene(300, seed=4)
    window = Window(torch.tensor([20, 2, 30]), torch.tensor([6, 15, 0]), 17, 21)
    assert_parity(params, viewmats, ks, window)


@needs_cpp
def test_parity_sh_coefficients():
    params, viewmats, ks = scene(250, seed=5)
    params[4] = torch.randn(250, 16, 3, generator=torch.Generator().manual_seed(9)) * 0.3
    assert_parity(params, viewmats, ks, sh_degree=3)


@needs_cpp
def test_empty_views():
    for params, viewmats, ks in (scene(0, seed=6), scene(40, seed=6, behind=40)):
        out, grads = render(params, viewmats, ks, "cpp")
        assert out.alpha.abs().max() == 0 and (out.radii == 0).all()
        assert all(torch.isfinite(gr).all() and gr.abs().sum() == 0 for gr in grads)


@needs_cpp
def test_projection_matches_torch():
    params, viewmats, ks = scene(300, seed=7, huge=5, behind=10)
    means, quats, scales, opacities, _ = params
    x0, y0 = torch.tensor([0, 3, 10]), torch.tensor([0, 2, 5])
    leaves = [[p.clone().requires_grad_(True) for p in (means, quats, scales)] for _ in range(2)]
    g = torch.Generator().manual_seed(1)
    w = [torch.randn(3, 300, k, generator=g) for k in (2, 3, 1)]
    grads, projs = [], []
    for fn, (m, q, s) in zip((project_gaussians, project_cpp), leaves):
        proj = fn(m, q, s, opacities, viewmats, ks, W, H, x0, y0, 30, 20)
        seen = proj.visible[..., None]
        loss = ((proj.means2d * w[0]).sum() + (proj.conics * w[1] * seen).sum()
                + (proj.depths[..., None] * w[2]).sum())
        grads.append(torch.autograd.grad(loss, [m, q, s]))
        projs.append(proj)
    a, b = projs
    assert torch.equal(a.radii, b.radii) and torch.allclose(a.depths, b.depths, atol=1e-5)
    assert torch.allclose(a.means2d, b.means2d, atol=1e-4)
    assert torch.allclose(a.conics[a.visible], b.conics[b.visible], rtol=1e-5, atol=1e-7)
    for name, ref, mine in zip(("means", "quats", "scales"), *grads):
        assert_close_grad(mine, ref, name, rel=1e-5)


@needs_cpp
def test_float64_falls_back_to_the_torch_path():
    params, viewmats, ks = scene(100, seed=8)
    params = [p.double() for p in params]
    a, grads_a = render(params, viewmats.double(), ks.double(), "torch")
    b, grads_b = render(params, viewmats.double(), ks.double(), "cpp")
    assert torch.equal(a.rgb, b.rgb) and all(torch.equal(x, y) for x, y in zip(grads_a, grads_b))


@needs_cpp
def test_threads_and_instruction_sets_agree(monkeypatch):
    """Images do not depend on the thread count nor on the SIMD build (each pixel sees the
    same float operations); gradients only up to the order of their sums."""
    params, viewmats, ks = scene(300, seed=9, huge=3)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        ref, grads_ref = render(params, viewmats, ks, "cpp")
        torch.set_num_threads(3)
        out, grads = render(params, viewmats, ks, "cpp")
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(out.rgb, ref.rgb) and torch.equal(out.alpha, ref.alpha)
    for name, mine, theirs in zip(("means", "quats", "scales", "opacities", "colors"), grads, grads_ref):
        assert_close_grad(mine, theirs, name, rel=1e-5)
    if not rasterize_cpp.simd().startswith("avx2"):
        return  # this CPU runs the baseline build only
    monkeypatch.setenv("RAINYSCAPE_RASTERIZER_SIMD", "baseline")
    assert rasterize_cpp.simd().startswith("baseline")
    out, grads = render(params, viewmats, ks, "cpp")
    assert torch.equal(out.rgb, ref.rgb) and torch.equal(out.alpha, ref.alpha)
    for name, mine, theirs in zip(("means", "quats", "scales", "opacities", "colors"), grads, grads_ref):
        assert_close_grad(mine, theirs, name, rel=1e-5)


@needs_cpp
def test_gradients_repeat_bit_for_bit_on_several_threads():
    """With several threads the gradients are the same on every call (tiles go to workers by a
    fixed rule, so each worker's float sums run in one order): what makes a resumed run
    match an uninterrupted one. Many tiles and few threads make a dynamic hand-out differ."""
    params, viewmats, ks = scene(300, seed=9, huge=3)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        runs = [render(params, viewmats, ks, "cpp")[1] for _ in range(4)]
    finally:
        torch.set_num_threads(threads)
    for grads in runs[1:]:
        for name, mine, first in zip(("means", "quats", "scales", "opacities", "colors"), grads, runs[0]):
            assert torch.equal(mine, first), name


@needs_cpp
def test_ellipse_binning_lists_fewer_pairs_than_boxes():
    """Tiles are listed where the alpha > 1/255 ellipse reaches, not where its bounding box
    does: slender, tilted Gaussians touch far fewer tiles (and the images still agree)."""
    params, viewmats, ks = scene(300, seed=10, cameras=1)
    params[2][:, 0] *= 6.0  # slender
    params[2][:, 1] *= 0.2
    with torch.no_grad():
        proj = project_gaussians(*params[:4], viewmats, ks, W, H)
    boxes = len(bin_gaussians(proj, W, H).gaussian_ids)
    assert binning_pairs(proj, W, H) < 0.85 * boxes
    assert_parity(params, viewmats, ks)


def test_explicit_cpp_that_cannot_run_is_a_config_error(monkeypatch):
    with pytest.raises(ConfigError, match="field.backend=cpp: it needs CPU tensors"):
        resolve_backend("cpp", torch.device("cuda"))  # resolving allocates nothing
    monkeypatch.setattr(rasterize_module, "cpp_available", lambda: False)
    monkeypatch.setattr(rasterize_module, "unavailable_reason",
                        lambda: "the compiled rasteriser did not import (test)")
    with pytest.raises(ConfigError, match="did not import"):
        resolve_backend("cpp", torch.device("cpu"))
    assert resolve_backend("auto", torch.device("cpu")) == "torch"


@needs_cpp
def test_absgrad_equals_the_torch_path():
    """The compiled backward's absolute 2D-mean gradient (``absgrad=True``) equals the torch
    path's, on several cameras and a window, with the plain gradients unchanged."""
    params, viewmats, ks = scene(300, seed=4, cameras=3)
    window = Window(torch.tensor([3, 0, 20]), torch.tensor([5, 9, 0]), 24, 20)
    outs = []
    for backend in ("torch", "cpp"):
        leaves = [p.detach().clone().requires_grad_(True) for p in params]
        out = rasterize(*leaves, viewmats, ks, W, H, window, backend=backend, absgrad=True)
        out.means2d.retain_grad()
        w = torch.randn(out.rgb.shape, generator=torch.Generator().manual_seed(1))
        (out.rgb * w).sum().backward()
        outs.append(out)
    a, b = outs
    assert_close_grad(b.means2d.absgrad, a.means2d.absgrad, "absgrad")
    assert_close_grad(b.means2d.grad, a.means2d.grad, "means2d")
    assert float(b.means2d.absgrad.sum()) > float(b.means2d.grad.abs().sum())
