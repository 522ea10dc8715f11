"""The Gaussian rasteriser: tiled torch path vs a dense per-pixel reference, windows,
projection in every dataparser convention, and gsplat agreement where CUDA is present."""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pytest
import torch

from rainyscape.cameras import Window
from rainyscape.errors import ConfigError
from rainyscape.fields.gaussians.projection import candidate_gaussians, project_gaussians
from rainyscape.fields.gaussians.rasterize import rasterize, resolve_backend
from rainyscape.fields.gaussians.rasterize_cpp import cpp_available
from rainyscape.fields.gaussians.rasterize_gsplat import (BUILD_MESSAGE, forget_gsplat_checks,
                                                          gsplat_installed, gsplat_usable)
from rainyscape.fields.gaussians.rasterize_torch import bin_gaussians, composite, min_sigma_in_boxes
from rainyscape.testing.reference_rasterizer import composite_dense
from rainyscape.fields.gaussians.sh import sh_to_rgb

W, H = 45, 37  # not multiples of the 16-pixel tile


def random_scene(n: int, seed: int, dtype=torch.float32, opaque: bool = False, cameras: int = 2):
    """Gaussians in a slab in front of camera 0; camera 1 is shifted and turned a little."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * torch.tensor([2.5, 2.0, 1.0], dtype=dtype)
    means[:, 2] += 4.0
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.2 + 0.03
    lo, span = (0.9, 0.099) if opaque else (0.05, 0.9)
    opacities = torch.rand(n, generator=g, dtype=dtype) * span + lo
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    viewmats = torch.eye(4, dtype=dtype).repeat(cameras, 1, 1)
    if cameras > 1:
        a = 0.1
        viewmats[1, :3, :3] = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0],
                                            [-math.sin(a), 0, math.cos(a)]], dtype=dtype)
        viewmats[1, :3, 3] = torch.tensor([0.2, -0.1, 0.3], dtype=dtype)
    ks = torch.tensor([[55.0, 0, 22.5], [0, 52.0, 18.0], [0, 0, 1]], dtype=dtype).repeat(cameras, 1, 1)
    return [means, quats, scales, opacities, colors], viewmats, ks


def render_both(params, viewmats, ks):
    """(tiled, dense) features (rgb + depth) and alpha for the same projection."""
    means, quats, scales, opacities, colors = params
    out = []
    for fn in (composite, composite_dense):
        proj = project_gaussians(means, quats, scales, opacities, viewmats, ks, W, H)
        feats = torch.cat([colors[None].expand(len(viewmats), -1, -1), proj.depths[..., None]], -1)
        out.append(fn(proj, feats, W, H))
    return out


@pytest.mark.parametrize("opaque", [False, True])
def test_tiled_matches_dense_reference(opaque):
    params, viewmats, ks = random_scene(300, seed=1, opaque=opaque)
    (f1, a1), (f2, a2) = render_both(params, viewmats, ks)
    assert f1.shape == (2, H, W, 4) and a1.shape == (2, H, W, 1)
    assert (a1 > 0.5).float().mean() > 0.3  # the scene covers the image
    if opaque:
        assert (a1 > 0.999).any()  # some pixels stop early (transmittance floor)
    assert torch.allclose(f1, f2, atol=1e-4) and torch.allclose(a1, a2, atol=1e-4)


@pytest.mark.parametrize("opaque", [False, True])
def test_gradients_match_dense_reference(opaque):
    params, viewmats, ks = random_scene(120, seed=2, dtype=torch.float64, opaque=opaque)
    for p in params:
        p.requires_grad_(True)
    g = torch.Generator().manual_seed(0)
    w_feat = torch.randn(2, H, W, 4, generator=g, dtype=torch.float64)
    w_alpha = torch.randn(2, H, W, 1, generator=g, dtype=torch.float64)
    grads = []
    for f, a in render_both(params, viewmats, ks):
        loss = (f * w_feat).sum() + (a * w_alpha).sum()
        grads.append(torch.autograd.grad(loss, params))
    for name, g1, g2 in zip(("means", "quats", "scales", "opacities", "colors"), *grads):
        assert g2.abs().max() > 0, name
        assert torch.allclose(g1, g2, rtol=1e-7, atol=1e-9 * float(g2.abs().max())), name


def test_large_gaussians_skip_the_quarter_split_and_match_dense_reference():
    """Gaussians spanning many tiles are composited on the 16 x 16 tiles (no 8 x 8 split);
    images and gradients still equal the dense reference."""
    import rainyscape.fields.gaussians.rasterize_torch as rt

    params, viewmats, ks = random_scene(80, seed=12, dtype=torch.float64)
    params[2] = params[2] * 4.0  # large: many tiles each
    with torch.no_grad():
        proj = project_gaussians(*params[:4], viewmats, ks, W, H)
    pairs = len(bin_gaussians(proj, W, H).gaussian_ids)
    assert pairs > rt.SPLIT_MAX_PAIRS * int(proj.visible.sum())  # the unsplit path
    for p in params:
        p.requires_grad_(True)
    g = torch.Generator().manual_seed(0)
    w_feat = torch.randn(2, H, W, 4, generator=g, dtype=torch.float64)
    grads, images = [], []
    for f, a in render_both(params, viewmats, ks):
        images.append((f, a))
        grads.append(torch.autograd.grad((f * w_feat).sum() + a.sum(), params))
    (f1, a1), (f2, a2) = images
    assert torch.allclose(f1, f2, atol=1e-10) and torch.allclose(a1, a2, atol=1e-10)
    for name, g1, g2 in zip(("means", "quats", "scales", "opacities", "colors"), *grads):
        assert torch.allclose(g1, g2, rtol=1e-7, atol=1e-9 * float(g2.abs().max())), name


def test_backward_replays_the_sweep_when_the_cache_is_full(monkeypatch):
    """Large renders do not keep the forward steps; the replayed backward is the same."""
    import rainyscape.fields.gaussians.rasterize_torch as rt

    params, viewmats, ks = random_scene(200, seed=8, opaque=True)
    for p in params:
        p.requires_grad_(True)

    def grads():
        out = rasterize(*params, viewmats, ks, W, H, backend="torch")
        return torch.autograd.grad((out.rgb * out.rgb).sum() + out.alpha.sum(), params)

    cached = grads()
    monkeypatch.setattr(rt, "CACHE_ELEMENTS", 0)
    monkeypatch.setattr(rt, "BLOCK_ELEMENTS", 1 << 14)  # many small steps
    for a, b in zip(cached, grads()):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6 * float(a.abs().max()))


def test_gradients_match_finite_differences():
    params, viewmats, ks = random_scene(40, seed=3, dtype=torch.float64)
    means, quats, scales, opacities, colors = params
    g = torch.Generator().manual_seed(1)
    w_rgb = torch.randn(2, H, W, 3, generator=g, dtype=torch.float64)

    def loss() -> torch.Tensor:
        out = rasterize(means, quats, scales, opacities, colors, viewmats, ks, W, H, backend="torch")
        return (out.rgb * w_rgb).sum() + out.alpha.sum()

    for p in params:
        p.requires_grad_(True)
    analytic = torch.autograd.grad(loss(), params)
    # The Gaussian that matters most: largest footprint contribution through its colour.
    k = int(torch.argmax(analytic[4].abs().sum(-1)))
    eps = 1e-6
    with torch.no_grad():
        for (i, p), idx in zip(enumerate(params), [(k, 0), (k, 2), (k, 1), (k,), (k, 1)]):
            old = float(p[idx])
            p[idx] = old + eps
            up = float(loss())
            p[idx] = old - eps
            down = float(loss())
            p[idx] = old
            numeric = (up - down) / (2 * eps)
            assert numeric == pytest.approx(float(analytic[i][idx]), rel=1e-5, abs=1e-6), i


def test_window_equals_crop_of_full_render():
    params, viewmats, ks = random_scene(400, seed=4)
    full = rasterize(*params, viewmats, ks, W, H)
    window = Window(torch.tensor([5, 29]), torch.tensor([0, 19]), 16, 18)  # second at the border
    part = rasterize(*params, viewmats, ks, W, H, window)
    assert part.rgb.shape == (2, 18, 16, 3)
    for b in range(2):
        x0, y0 = int(window.x0[b]), int(window.y0[b])
        crop = slice(y0, y0 + 18), slice(x0, x0 + 16)
        assert torch.allclose(part.rgb[b], full.rgb[b][crop], atol=1e-6)
        assert torch.allclose(part.alpha[b], full.alpha[b][crop], atol=1e-6)
        assert torch.allclose(part.depth[b], full.depth[b][crop], atol=1e-4)


def test_window_bins_only_its_tiles():
    """A patch costs a patch: only its tiles are composited, with fewer intersections."""
    params, viewmats, ks = random_scene(2000, seed=5, cameras=1)
    means, quats, scales, opacities, _ = params
    size = (160, 128)
    ks = torch.tensor([[[200.0, 0, 80], [0, 200, 64], [0, 0, 1]]])  # the slab fills the image
    full = project_gaussians(means, quats, scales, opacities, viewmats, ks, *size)
    win = project_gaussians(means, quats, scales, opacities, viewmats, ks, *size,
                            torch.tensor([48]), torch.tensor([32]), 32, 32)
    b_full, b_win = bin_gaussians(full, *size), bin_gaussians(win, 32, 32)
    assert len(b_win.tile_count) == 4 and len(b_full.tile_count) == 80
    assert len(b_win.gaussian_ids) < len(b_full.gaussian_ids) / 8
    assert win.visible.sum() < full.visible.sum() / 2


def test_min_sigma_in_boxes_matches_a_dense_search():
    g = torch.Generator().manual_seed(12)
    m = 500
    lo = (torch.rand(m, 2, generator=g, dtype=torch.float64) - 0.5) * 20
    hi = lo + torch.rand(m, 2, generator=g, dtype=torch.float64) * 8
    cov = torch.randn(m, 2, 2, generator=g, dtype=torch.float64)
    cov = cov @ cov.transpose(1, 2) + 0.3 * torch.eye(2, dtype=torch.float64)
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], -1)
    t = torch.linspace(0, 1, 201, dtype=torch.float64)
    dx = lo[:, 0, None, None] + (hi - lo)[:, 0, None, None] * t[None, None, :]
    dy = lo[:, 1, None, None] + (hi - lo)[:, 1, None, None] * t[None, :, None]
    a, b, c = (v[:, None, None] for v in conics.unbind(-1))
    dense = (0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy).flatten(1).amin(1)
    exact = min_sigma_in_boxes(lo, hi, conics)
    assert (exact <= dense + 1e-12).all()  # a true minimum: never above a sampled point
    assert torch.allclose(exact, dense, rtol=1e-3, atol=1e-3)  # and reached on the grid
    assert (exact == 0).any() and (exact > 0).any()


def test_culling_keeps_every_gaussian_the_projection_sees():
    params, viewmats, ks = random_scene(3000, seed=9)
    means, quats, scales, opacities, _ = params
    varied = scales * torch.rand(len(scales), 1, generator=torch.Generator().manual_seed(0)) * 3
    for x0, y0, w, h in ((0, 0, W, H), (30, 4, 16, 16), (-5, 20, 12, 30)):
        args = (torch.tensor([x0, x0 + 3]), torch.tensor([y0, y0 - 2]), w, h)
        ids = candidate_gaussians(means, varied, opacities, viewmats, ks, W, H, *args)
        seen = project_gaussians(means, quats, varied, opacities, viewmats, ks, W, H,
                                 *args).visible.any(0).nonzero().squeeze(1)
        assert set(seen.tolist()) <= set(ids.tolist())
    # A 32 x 32 patch of a 160 x 128 image that the slab fills: most are culled, and the
    # bound is not much looser than the projection.
    ks = torch.tensor([[[200.0, 0, 80], [0, 200, 64], [0, 0, 1]]])
    args = (torch.tensor([48]), torch.tensor([32]), 32, 32)
    scales = scales * 0.2  # trained scenes: many small Gaussians
    ids = candidate_gaussians(means, scales, opacities, viewmats[:1], ks, 160, 128, *args)
    seen = project_gaussians(means, quats, scales, opacities, viewmats[:1], ks, 160, 128,
                             *args).visible.sum()
    assert len(ids) < len(means) / 4 and len(ids) < 2 * seen


def test_culled_window_matches_dense_reference():
    """The rasteriser's culled path: images and gradients of every parameter equal the
    dense reference over all Gaussians; the 2D means' gradient has all N rows."""
    params, viewmats, ks = random_scene(400, seed=10, dtype=torch.float64)
    for p in params:
        p.requires_grad_(True)
    means, quats, scales, opacities, colors = params
    window = Window(torch.tensor([20, 2]), torch.tensor([6, 15]), 16, 16)
    ids = candidate_gaussians(means, scales, opacities, viewmats, ks, W, H, window.x0,
                              window.y0, 16, 16)
    assert len(ids) < 400  # the culled path is the one under test
    out = rasterize(*params, viewmats, ks, W, H, window, backend="torch")
    out.means2d.retain_grad()
    proj = project_gaussians(means, quats, scales, opacities, viewmats, ks, W, H,
                             window.x0, window.y0, 16, 16)
    feats = torch.cat([colors[None].expand(2, -1, -1), proj.depths[..., None]], -1)
    ref, ref_alpha = composite_dense(proj, feats, 16, 16)
    assert torch.allclose(out.rgb, ref[..., :3], atol=1e-10)
    assert torch.allclose(out.alpha, ref_alpha, atol=1e-10)
    g = torch.Generator().manual_seed(3)
    w_rgb = torch.randn(2, 16, 16, 3, generator=g, dtype=torch.float64)
    mine = torch.autograd.grad((out.rgb * w_rgb).sum() + out.alpha.sum(), params, retain_graph=True)
    theirs = torch.autograd.grad((ref[..., :3] * w_rgb).sum() + ref_alpha.sum(), params)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors"), mine, theirs):
        assert torch.allclose(a, b, rtol=1e-7, atol=1e-9 * float(b.abs().max())), name
    out2 = rasterize(*params, viewmats, ks, W, H, window, backend="torch")
    out2.means2d.retain_grad()
    (out2.rgb * w_rgb).sum().backward()
    assert out2.means2d.grad.shape == (2, 400, 2)
    culled = (out2.radii == 0).all(-1)
    assert culled.any() and (out2.means2d.grad[culled] == 0).all()
    assert out2.means2d.grad[~culled].abs().sum() > 0


def test_sh_coefficients_equal_precomputed_colours():
    params, viewmats, ks = random_scene(200, seed=11)
    means, quats, scales, opacities, _ = params
    coeffs = torch.randn(200, 9, 3, generator=torch.Generator().manual_seed(1)) * 0.3
    centres = torch.linalg.inv(viewmats)[:, :3, 3]
    dirs = torch.nn.functional.normalize(means[None] - centres[:, None], dim=-1)
    colors = sh_to_rgb(coeffs, dirs, 2)  # (C, N, 3): differs per camera
    a = rasterize(means, quats, scales, opacities, coeffs, viewmats, ks, W, H, sh_degree=2)
    b = rasterize(means, quats, scales, opacities, colors, viewmats, ks, W, H)
    assert torch.allclose(a.rgb, b.rgb, atol=1e-6)


def test_background_empty_and_culled_scenes():
    params, viewmats, ks = random_scene(0, seed=6)
    bg = torch.tensor([0.2, 0.4, 0.6])
    out = rasterize(*params, viewmats, ks, W, H, backgrounds=bg)
    assert torch.allclose(out.rgb, bg.expand(2, H, W, 3)) and out.alpha.abs().max() == 0
    params, viewmats, ks = random_scene(50, seed=6)
    params[0] = params[0] * torch.tensor([1.0, 1.0, -1.0])  # all behind the cameras
    for p in params:
        p.requires_grad_(True)
    out = rasterize(*params, viewmats, ks, W, H)
    assert out.alpha.abs().max() == 0 and (out.radii == 0).all()
    out.rgb.sum().backward()
    assert all(torch.isfinite(p.grad).all() and p.grad.abs().max() == 0 for p in params)


def test_backend_choice():
    # On the CPU, auto is the compiled kernel when it was built (tests/test_rasterize_cpp.py
    # checks that it was, where a compiler is present), else the torch rasteriser.
    assert resolve_backend("auto", torch.device("cpu")) == ("cpp" if cpp_available() else "torch")
    assert resolve_backend("torch", torch.device("cpu")) == "torch"
    with pytest.raises(ConfigError):
        resolve_backend("gsplat", torch.device("cpu"))
    with pytest.raises(ConfigError):
        resolve_backend("opengl", torch.device("cpu"))


@pytest.fixture
def fresh_gsplat_checks():
    forget_gsplat_checks()
    yield
    forget_gsplat_checks()


@pytest.mark.skipif(gsplat_installed(), reason="gsplat is installed here")
def test_missing_gsplat_on_cuda_falls_back_with_one_warning(fresh_gsplat_checks, capsys):
    """auto on a CUDA device without gsplat: the torch rasteriser, one warning, no traceback
    (resolving needs no GPU: nothing is allocated)."""
    cuda = torch.device("cuda")
    assert resolve_backend("auto", cuda) == "torch"
    assert resolve_backend("auto", cuda) == "torch"
    err = capsys.readouterr().err
    assert err.count("warning") == 1 and "gsplat is not installed" in err
    assert "torch rasteriser" in err and "rainyscape[cuda]" in err and "Traceback" not in err
    with pytest.raises(ConfigError, match="backend=gsplat"):
        resolve_backend("gsplat", cuda)


def fake_gsplat(root, backend_source: str = "_C = object()\n", init_source: str = ""):
    pkg = root / "gsplat"
    (pkg / "cuda").mkdir(parents=True)
    (pkg / "__init__.py").write_text(init_source)
    (pkg / "cuda" / "__init__.py").write_text("")
    (pkg / "cuda" / "_backend.py").write_text(backend_source)
    return root


@pytest.mark.parametrize("case, init, backend, expected", [
    ("import error", "raise OSError('libcudart.so.12: cannot open shared object file')", "",
     "gsplat does not import (OSError: libcudart.so.12"),
    ("build error", "", "raise RuntimeError('Error building extension gsplat_cuda')",
     "did not build or load (RuntimeError: Error building extension"),
    ("no toolkit", "", "_C = None\n", "no CUDA toolkit"),
])
def test_broken_gsplat_falls_back_with_one_warning(fresh_gsplat_checks, tmp_path, monkeypatch,
                                                   capsys, case, init, backend, expected):
    fake_gsplat(tmp_path, backend or "_C = object()\n", init)
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in [m for m in sys.modules if m == "gsplat" or m.startswith("gsplat.")]:
        monkeypatch.delitem(sys.modules, name)
    forget_gsplat_checks()
    calls = []
    assert not gsplat_usable(torch.device("cuda"), smoke_test=calls.append)
    assert not gsplat_usable(torch.device("cuda"), smoke_test=calls.append)
    err = capsys.readouterr().err
    assert err.count("rainyscape: warning:") == 1 and expected in err, err
    assert calls == []  # nothing ran on the device
    # the first use of a gsplat that must build its kernels says so
    if case != "import error":
        assert BUILD_MESSAGE in err


def test_working_gsplat_builds_once_with_a_message(fresh_gsplat_checks, tmp_path, monkeypatch, capsys):
    fake_gsplat(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in [m for m in sys.modules if m == "gsplat" or m.startswith("gsplat.")]:
        monkeypatch.delitem(sys.modules, name)
    forget_gsplat_checks()
    calls = []
    assert gsplat_usable(torch.device("cuda"), smoke_test=calls.append)
    assert gsplat_usable(torch.device("cuda"), smoke_test=calls.append)
    err = capsys.readouterr().err
    assert err.count(BUILD_MESSAGE) == 1 and "warning" not in err and len(calls) == 1
    # a kernel that fails its first render: one warning, the torch rasteriser

    def failing(device):
        raise RuntimeError("CUDA error: no kernel image is available for execution on the device")

    forget_gsplat_checks()
    assert not gsplat_usable(torch.device("cuda"), smoke_test=failing)
    err = capsys.readouterr().err
    assert err.count("rainyscape: warning:") == 1 and "failed a test render" in err


# ---------------------------------------------------------------- conventions


def render_peak(scene, view: int, point: np.ndarray) -> tuple[float, float]:
    """Render one small bright Gaussian at a point of the input's world frame in ``view``
    of the parsed scene; return the intensity-weighted centroid (x, y) in pixels."""
    p = torch.as_tensor(point, dtype=torch.float64)[None]
    hom = torch.cat([p, torch.ones(1, 1, dtype=torch.float64)], 1) @ scene.transform.double().T
    mean = (hom[:, :3] * scene.scale).float()
    cams = scene.cameras[[view]]
    depth = float((cams.w2c()[0, :3, :3] @ mean[0] + cams.w2c()[0, :3, 3])[2])
    sigma_px = 1.2
    scale = torch.full((1, 3), sigma_px * depth / float(cams.fx[0]))
    out = rasterize(mean, torch.tensor([[1.0, 0, 0, 0]]), scale, torch.tensor([0.99]),
                    torch.ones(1, 3), cams.w2c(), cams.K(), scene.width, scene.height, eps2d=0.0)
    img = out.alpha[0, ..., 0].double()
    assert img.sum() > 1.0, "the point should be in view"
    ys, xs = torch.meshgrid(torch.arange(scene.height) + 0.5, torch.arange(scene.width) + 0.5,
                            indexing="ij")
    return float((img * xs).sum() / img.sum()), float((img * ys).sum() / img.sum())


def maya_expected(tiny_scene_dir, view: int):
    """Maya camera model, computed here from cameras.csv: world Y up, camera looking down
    its -Z, rotation Rz Ry Rx (XYZ order), f_px = focal / aperture * width, centred."""
    import csv

    row = list(csv.DictReader(open(tiny_scene_dir / "cameras.csv")))[view]
    pos = np.array([float(row[f"Position {a}"]) for a in "XYZ"])
    rx, ry, rz = (math.radians(float(row[f"Rotation {a}"])) for a in "XYZ")
    rot_x = np.array([[1, 0, 0], [0, math.cos(rx), -math.sin(rx)], [0, math.sin(rx), math.cos(rx)]])
    rot_y = np.array([[math.cos(ry), 0, math.sin(ry)], [0, 1, 0], [-math.sin(ry), 0, math.cos(ry)]])
    rot_z = np.array([[math.cos(rz), -math.sin(rz), 0], [math.sin(rz), math.cos(rz), 0], [0, 0, 1]])
    rot = rot_z @ rot_y @ rot_x  # camera axes in world: columns x right, y up, z back
    point = pos - 3.0 * rot[:, 2] + 0.4 * rot[:, 0] - 0.3 * rot[:, 1]
    cam = rot.T @ (point - pos)
    w = 48
    f = float(row["Focal Length"]) / float(row["Horizontal Aperture"]) * w
    return point, (w / 2 + f * cam[0] / -cam[2], w / 2 - f * cam[1] / -cam[2])


def test_projection_maya_csv(tiny_scene_dir, tiny_scene):
    point, expected = maya_expected(tiny_scene_dir, view=5)
    assert render_peak(tiny_scene, 5, point) == pytest.approx(expected, abs=0.02)


def test_projection_llff(tiny_scene, tmp_path):
    from rainyscape.dataparsers.llff import LLFFParser
    from rainyscape.dataparsers.writers import write_llff

    write_llff(tiny_scene, tmp_path)
    raw = np.load(tmp_path / "poses_bounds.npy")[3, :15].reshape(3, 5)  # LLFF: down, right, back
    down, right, back, centre = raw[:, 0], raw[:, 1], raw[:, 2], raw[:, 3]
    h, w, f = raw[:, 4]
    point = centre - 2.5 * back + 0.3 * right + 0.2 * down
    d = point - centre
    expected = (w / 2 + f * d @ right / (d @ -back), h / 2 + f * d @ down / (d @ -back))
    scene = LLFFParser(LLFFParser.Config()).parse(tmp_path)
    assert render_peak(scene, 3, point) == pytest.approx(expected, abs=0.02)


def test_projection_transforms_json(tiny_scene, tmp_path):
    from rainyscape.dataparsers.transforms_json import TransformsJsonParser
    from rainyscape.dataparsers.writers import write_transforms_json

    write_transforms_json(tiny_scene, tmp_path)
    meta = json.loads((tmp_path / "transforms.json").read_text())
    frame = meta["frames"][2]
    c2w = np.array(frame["transform_matrix"])  # OpenGL: x right, y up, z back
    point = c2w[:3, 3] - 2.0 * c2w[:3, 2] - 0.25 * c2w[:3, 0] + 0.3 * c2w[:3, 1]
    cam = c2w[:3, :3].T @ (point - c2w[:3, 3])
    expected = (frame["cx"] + frame["fl_x"] * cam[0] / -cam[2],
                frame["cy"] - frame["fl_y"] * cam[1] / -cam[2])
    scene = TransformsJsonParser(TransformsJsonParser.Config()).parse(tmp_path)
    assert render_peak(scene, 2, point) == pytest.approx(expected, abs=0.02)


def test_projection_colmap(tmp_path):
    import imageio.v3 as iio

    from rainyscape.dataparsers.colmap import ColmapParser

    # One PINHOLE camera, world-to-camera = rotation of 30 degrees about y, then t.
    a = math.radians(30)
    q = (math.cos(a / 2), 0.0, math.sin(a / 2), 0.0)
    t = np.array([0.3, -0.2, 4.0])
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text("1 PINHOLE 40 30 38 36 21 14.5\n")
    lines = [f"{i + 1} {q[0]} {q[1]} {q[2]} {q[3]} {t[0] + 0.1 * i} {t[1]} {t[2]} 1 v{i}.png\n"
             + ("20 15 1\n" if i == 0 else "\n") for i in range(3)]
    (model / "images.txt").write_text("".join(lines))
    (model / "points3D.txt").write_text("1 0 0 0 255 255 255 0.1 1 0\n")
    (tmp_path / "images").mkdir()
    for i in range(3):
        iio.imwrite(tmp_path / "images" / f"v{i}.png", np.zeros((30, 40, 3), np.uint8))
    rot = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
    point = np.array([0.4, 0.3, -0.5])
    cam = rot @ point + t + np.array([0.1, 0, 0])  # view 1
    expected = (21 + 38 * cam[0] / cam[2], 14.5 + 36 * cam[1] / cam[2])
    scene = ColmapParser(ColmapParser.Config(holdout_every=0)).parse(tmp_path)
    assert render_peak(scene, 1, point) == pytest.approx(expected, abs=0.02)


# ----------------------------------------------------------------------- CUDA


@pytest.mark.skipif(not (torch.cuda.is_available() and gsplat_installed()),
                    reason="needs CUDA and gsplat (pip install 'rainyscape[cuda]')")
def test_gsplat_agrees_with_torch_path():
    params, viewmats, ks = random_scene(500, seed=7)
    dev = torch.device("cuda")
    cuda = [p.to(dev).requires_grad_(True) for p in params]
    cpu = [p.clone().requires_grad_(True) for p in params]
    a = rasterize(*cuda, viewmats.to(dev), ks.to(dev), W, H, backend="gsplat")
    b = rasterize(*cpu, viewmats, ks, W, H, backend="torch")
    assert (a.rgb.cpu() - b.rgb).abs().max() < 2e-3
    assert (a.alpha.cpu() - b.alpha).abs().max() < 2e-3
    assert (a.depth.cpu() - b.depth).abs().mean() < 1e-3
    same = ((a.radii.cpu() > 0).all(-1) == (b.radii > 0).all(-1)).float().mean()
    assert same > 0.99  # ceil() of fast-math radii may differ at the margin
    a.rgb.sum().backward()
    b.rgb.sum().backward()
    for pc, pt in zip(cuda, cpu):
        assert (pc.grad.cpu() - pt.grad).norm() < 1e-2 * pt.grad.norm()
    # Windows: gsplat bounds its Jacobian clamp by the window, not the image, so large
    # Gaussians centred well outside the window may differ a little at its border.
    window = Window(torch.tensor([3, 20]), torch.tensor([4, 10]), 24, 24)
    a = rasterize(*cuda, viewmats.to(dev), ks.to(dev), W, H, window, backend="gsplat")
    b = rasterize(*cpu, viewmats, ks, W, H, window, backend="torch")
    assert (a.rgb.cpu() - b.rgb).abs().mean() < 1e-3
    assert (a.rgb.cpu() - b.rgb).abs().max() < 5e-2


def test_absgrad_sums_each_pixels_absolute_gradient():
    """``absgrad=True`` (AbsGS, gsplat's): ``means2d.absgrad`` is, per Gaussian, the sum over
    pixels of |d loss_pixel / d mean2d| -- computed here pixel by pixel -- on the culled
    path (all N rows); it is at least |grad| and larger where pixels pull opposite ways."""
    params, viewmats, ks = random_scene(60, seed=12, dtype=torch.float64)
    params[0].requires_grad_(True)
    window = Window(torch.tensor([20, 2]), torch.tensor([6, 15]), 6, 6)
    g = torch.Generator().manual_seed(5)
    w_rgb = torch.randn(2, 6, 6, 3, generator=g, dtype=torch.float64)

    def render(weights):
        out = rasterize(*params, viewmats, ks, W, H, window, backend="torch", absgrad=True)
        out.means2d.retain_grad()
        (out.rgb * weights).sum().backward()
        return out

    out = render(w_rgb)
    expected = torch.zeros(2, 60, 2, dtype=torch.float64)
    for c in range(2):
        for y in range(6):
            for x in range(6):
                one = torch.zeros_like(w_rgb)
                one[c, y, x] = w_rgb[c, y, x]
                expected += render(one).means2d.grad.abs()
    assert out.means2d.absgrad.shape == (2, 60, 2)
    assert torch.allclose(out.means2d.absgrad, expected, rtol=1e-9, atol=1e-12)
    assert bool((out.means2d.absgrad >= out.means2d.grad.abs() - 1e-12).all())
    assert float((out.means2d.absgrad - out.means2d.grad.abs()).max()) > 0.1 * float(expected.max())
    plain = rasterize(*params, viewmats, ks, W, H, window, backend="torch")
    assert not hasattr(plain.means2d, "absgrad")  # only when asked for
