"""The grid field's compiled first pass (fields/grid_march.py) against its dense torch pass:
the same live samples (rays, ranks, places, lengths, grid points, densities) in every layout,
the same render and gradients from either; empty space costs no samples; and the extension
was built wherever a C++ compiler is present."""

from __future__ import annotations

import shutil

import pytest
import torch

from rainyscape.cameras import Window, pixel_rays
from rainyscape.fields import grid_march
from rainyscape.fields.grid import GridField

from _scenes import forward_facing_scene

needs_cpp = pytest.mark.skipif(not grid_march.cpp_available(),
                               reason=grid_march.unavailable_reason() or "built")


def test_extension_is_built_where_a_compiler_is():
    if not (shutil.which("g++") or shutil.which("c++")):
        pytest.skip("no C++ compiler here: the dense torch pass is the CPU path")
    assert grid_march.cpp_available(), (f"{grid_march.unavailable_reason()}: a C++ compiler is "
                                        "present, so 'pip install -e .' should have built it")


def _structured_field(scene, **options) -> GridField:
    """A field with uneven density (rays turn opaque at different places) and an occupancy
    grid that empties about half the cells."""
    torch.manual_seed(0)
    config = GridField.Config(resolution_init=24, resolution_final=24, occupancy_resolution=16,
                              **options)
    field = GridField(config, scene)
    with torch.no_grad():
        field.density_grid.plane.normal_(0.0, 1.5)
        field.density_grid.line.normal_(0.0, 1.5)
        field.occupancy.set(torch.rand(16, 16, 16) < 0.5)
    return field


def _rays(field, scene, views):
    cams = scene.cameras[views]
    window = Window.full(cams)
    ys, xs = window.pixel_grid()
    rays = pixel_rays(cams, xs, ys)
    return field.space.sample_rays(rays.origins.reshape(-1, 3), rays.directions.reshape(-1, 3))


def _both(field, rays, training: bool):
    field.train(training)
    torch.manual_seed(1)
    dense = field._march_dense(rays)
    torch.manual_seed(1)
    compiled = field._march(rays)
    return dense, compiled


@needs_cpp
@pytest.mark.parametrize("layout", ["contract", "box", "ndc"])
@pytest.mark.parametrize("training", [True, False])
def test_compiled_pass_keeps_the_dense_pass_samples(tiny_scene, layout, training):
    scene = forward_facing_scene() if layout == "ndc" else tiny_scene
    field = _structured_field(scene, layout=layout)
    dense, compiled = _both(field, _rays(field, scene, [0, 1]), training)
    assert len(dense.ray) > 100 and compiled.slots == dense.slots
    assert torch.equal(compiled.ray, dense.ray) and torch.equal(compiled.rank, dense.rank)
    for name in ("t", "delta", "g", "sigma"):
        assert torch.allclose(getattr(compiled, name), getattr(dense, name), rtol=1e-5, atol=1e-6), name
    assert int(compiled.evaluated) == len(compiled.ray) <= int(dense.evaluated)


@needs_cpp
def test_compiled_pass_renders_and_trains_as_the_dense_pass(tiny_scene, monkeypatch):
    field = _structured_field(tiny_scene, near_gradient=1.0)
    field.request({"distortion", "front_weight"})
    cams = tiny_scene.cameras[[0]]
    window = Window.full(cams)
    outputs = []
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setattr(grid_march, "_ext", None)
        field.train().zero_grad(set_to_none=True)
        torch.manual_seed(2)
        out = field.render(cams, window)
        loss = out.rgb.square().mean() + out.extras["distortion"].mean() + out.extras["front_weight"].mean()
        loss.backward()
        outputs.append((out, [p.grad.clone() for p in field.parameters() if p.grad is not None]))
    (a, grads_a), (b, grads_b) = outputs
    for name in ("rgb", "depth", "acc"):
        assert torch.allclose(getattr(a, name), getattr(b, name), atol=1e-5), name
    for name in ("distortion", "front_weight"):
        assert torch.allclose(a.extras[name], b.extras[name], atol=1e-5), name
    assert len(grads_a) == len(grads_b) == len(list(field.parameters()))
    for ga, gb in zip(grads_a, grads_b):
        assert torch.allclose(ga, gb, rtol=1e-3, atol=1e-6)


@needs_cpp
def test_empty_space_costs_no_samples(tiny_scene):
    """With every cell empty only the last sample of each ray is live: the one that takes the
    light that is left."""
    field = _structured_field(tiny_scene)
    rays = _rays(field, tiny_scene, [0])
    field.occupancy.set(torch.zeros(16, 16, 16, dtype=torch.bool))
    live = field.eval()._march(rays)
    n_rays = rays.origins.shape[0]
    assert torch.equal(live.ray, torch.arange(n_rays)) and bool((live.delta > 1e9).all())


@needs_cpp
def test_compiled_pass_is_the_same_on_any_number_of_threads(tiny_scene):
    field = _structured_field(tiny_scene).eval()
    rays = _rays(field, tiny_scene, [0, 1, 2])
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = field._march(rays)
        torch.set_num_threads(3)
        three = field._march(rays)
    finally:
        torch.set_num_threads(threads)
    for name in ("ray", "rank", "t", "delta", "g", "sigma"):
        assert torch.equal(getattr(one, name), getattr(three, name)), name
