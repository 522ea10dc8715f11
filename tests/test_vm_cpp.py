"""The compiled vector-matrix lookup (fields/vm_cpp.py) against the torch lookup of the same
tables: features and both tables' gradients, on uneven lattices, points on and outside the
edges; repeatable gradients on several threads; and that the extension was built wherever a
C++ compiler is present (a silent build failure would quietly fall back to torch)."""

from __future__ import annotations

import shutil

import pytest
import torch
from torch import Tensor

from rainyscape.fields import vm_cpp
from rainyscape.fields.feature_grids import VMTables

needs_cpp = pytest.mark.skipif(not vm_cpp.cpp_available(), reason=vm_cpp.unavailable_reason() or "built")


def test_extension_is_built_where_a_compiler_is():
    if not (shutil.which("g++") or shutil.which("c++")):
        pytest.skip("no C++ compiler here: the torch lookup is the CPU path")
    assert vm_cpp.cpp_available(), (f"{vm_cpp.unavailable_reason()}: a C++ compiler is present, "
                                    "so 'pip install -e .' should have built it")


def _features_and_grads(tables: VMTables, points: Tensor, weights: Tensor, compiled: bool):
    saved = vm_cpp._ext
    if not compiled:
        vm_cpp._ext = None
    try:
        tables.zero_grad(set_to_none=True)
        feats = tables.features(points)
        (feats * weights).sum().backward()
        return feats.detach(), tables.plane.grad.clone(), tables.line.grad.clone()
    finally:
        vm_cpp._ext = saved


@needs_cpp
@pytest.mark.parametrize("components,sizes", [(1, (2, 2, 2)), (5, (7, 4, 9)), (16, (33, 17, 20))])
def test_matches_the_torch_lookup(components, sizes):
    g = torch.Generator().manual_seed(components)
    tables = VMTables(components, sizes)
    points = torch.rand(2000, 3, generator=g) * 2.4 - 1.2  # some outside: clamped to the edge
    points[:8] = torch.tensor([-1.0, 1.0, 0.0])  # exactly on the corners
    weights = torch.randn(2000, 3 * components, generator=g)
    want = _features_and_grads(tables, points, weights, compiled=False)
    got = _features_and_grads(tables, points, weights, compiled=True)
    for w, h in zip(want, got):
        torch.testing.assert_close(h, w, rtol=1e-5, atol=1e-6)
    assert got[1].abs().sum() > 0 and got[2].abs().sum() > 0


@needs_cpp
def test_the_forward_layout_matches_the_mode_major_features():
    tables = VMTables(3, (5, 6, 7))
    points = torch.rand(100, 3) * 2 - 1
    with torch.no_grad():
        assert torch.equal(tables(points).transpose(0, 1).reshape(100, -1), tables.features(points))


@needs_cpp
def test_gradients_repeat_bit_for_bit_on_several_threads():
    tables = VMTables(8, (40, 30, 20))
    points = torch.rand(20000, 3) * 2 - 1  # ten blocks of points: every worker gets several
    weights = torch.randn(20000, 24)
    threads = torch.get_num_threads()
    torch.set_num_threads(3)
    try:
        first = _features_and_grads(tables, points, weights, compiled=True)
        again = _features_and_grads(tables, points, weights, compiled=True)
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(first, again):
        assert torch.equal(a, b)


def test_the_backward_runs_on_one_thread_when_its_points_are_few_for_the_table():
    # colour table at 512^3 (786432 rows): a step's 20k shaded samples go serial, 80k parallel
    assert vm_cpp.backward_threads(20_000, 786_432, 2) == 1
    assert vm_cpp.backward_threads(80_000, 786_432, 2) == 2
    assert vm_cpp.backward_threads(20_000, 196_608, 2) == 2  # the 256^3 table
    assert vm_cpp.backward_threads(10, 100, 0) == 1


@needs_cpp
def test_gradients_accumulate_in_a_buffer_the_tables_keep_between_steps():
    tables = VMTables(4, (9, 7, 5))
    points = torch.rand(500, 3) * 2 - 1
    weights = torch.randn(500, 12)
    first = _features_and_grads(tables, points, weights, compiled=True)
    buffer = tables.plane.grad
    # a second step after zero_grad(set_to_none): the same gradient, in the same storage
    again = _features_and_grads(tables, points, weights, compiled=True)
    assert tables.plane.grad is buffer
    for a, b in zip(first, again):
        assert torch.equal(a, b)
    # two backward passes before the step add up, as autograd's own accumulation does
    tables.zero_grad(set_to_none=True)
    for _ in range(2):
        (tables.features(points) * weights).sum().backward()
    torch.testing.assert_close(tables.plane.grad, 2 * first[1])
    torch.testing.assert_close(tables.line.grad, 2 * first[2])
    # a table that is not a leaf (scaled here) still gets its gradient through autograd
    tables.zero_grad(set_to_none=True)
    plane = tables.plane * 2.0
    feats = vm_cpp.vm_lookup(plane, tables.line, points, tables.layout())
    (feats * weights).sum().backward()
    assert tables.plane.grad.abs().sum() > 0
