"""The compiled vector-matrix lookup (csrc/vm_lookup.cpp, built by setup.py at install time):
:class:`feature_grids.VMTables`' features and their gradients in C++, for float32 CPU tables.

Same maths as the torch path (bilinear plane taps times linear line taps, aligned corners,
coordinates clamped to [-1, 1]); gradients go to the two tables, not to the points (nor do
they on the torch path: the fields sample at fixed points). Threads: ``torch.get_num_threads()``.

A leaf table's gradient is added straight into its ``.grad``, made (when None) from a buffer
the table keeps between steps: a fresh table-sized gradient each step cost more than the
backward itself (page faults: a 512^3 colour table's 75 MB took 59 ms to allocate zeroed,
5 ms to zero again; docs/benchmarks.md, "The tables' gradients kept between steps"). So the
tables' gradients reach ``.backward()``, not ``torch.autograd.grad``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from rainyscape.fields.compiled import load

_ext, _IMPORT_ERROR = load("rainyscape.fields._vm_cpp")


def cpp_available() -> bool:
    """Whether the compiled extension was built and imports."""
    return _ext is not None


def unavailable_reason() -> str:
    """Why the extension cannot be used ('' when it can)."""
    return "" if _ext is not None else f"the compiled vm lookup did not import ({_IMPORT_ERROR})"


def usable(plane: Tensor, points: Tensor) -> bool:
    """Whether :func:`vm_lookup` can take these: float32 tables and points on the CPU."""
    return (_ext is not None and plane.device.type == "cpu" and plane.dtype == torch.float32
            and points.device.type == "cpu")


class _VMLookup(torch.autograd.Function):
    @staticmethod
    def forward(ctx, plane: Tensor, line: Tensor, points: Tensor, layout: tuple) -> Tensor:
        plane_c, line_c = plane.detach().contiguous(), line.detach().contiguous()
        points_c = points.detach().to(torch.float32).contiguous()
        out = torch.empty(points_c.shape[0], 3 * layout[0])
        _ext.forward(layout, plane_c.data_ptr(), line_c.data_ptr(), points_c.data_ptr(),
                     points_c.shape[0], out.data_ptr(), torch.get_num_threads())
        ctx.keep = (plane_c, line_c, points_c, layout)
        ctx.tables = (plane, line)
        return out

    @staticmethod
    def backward(ctx, grad: Tensor):
        return (*tables_backward(ctx.tables, *ctx.keep[:3], grad, ctx.keep[3]), None, None)


def kept_grad(table: Tensor) -> Tensor:
    """``table.grad``; when None, the buffer the table keeps between steps, zeroed."""
    if table.grad is None:
        buf = getattr(table, "_kept_grad", None)
        if buf is None or buf.shape != table.shape:
            buf = torch.zeros_like(table)
            table._kept_grad = buf
        else:
            buf.zero_()
        table.grad = buf
    return table.grad


def tables_backward(tables: tuple[Tensor, Tensor], plane: Tensor, line: Tensor, points: Tensor,
                    grad: Tensor, layout: tuple[int, ...]) -> tuple[Tensor | None, Tensor | None]:
    """What an autograd backward returns for the tables (plane, line) from the features'
    gradient ``grad``: None for leaf tables, whose gradients go straight into their ``.grad``,
    else the gradients themselves. ``plane``, ``line``, ``points``: contiguous float32 copies."""
    if all(t.is_leaf and t.requires_grad for t in tables):
        grads = [kept_grad(t) for t in tables]
        if all(g.is_contiguous() and g.dtype == torch.float32 for g in grads):
            vm_backward(plane, line, points, grad, layout, into=grads)
            return None, None
    return vm_backward(plane, line, points, grad, layout)


def vm_backward(plane: Tensor, line: Tensor, points: Tensor, grad: Tensor, layout: tuple[int, ...],
                into: list[Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """The tables' gradients (plane, line) from the features' gradient ``grad`` (P, 3 C) at
    ``points`` (P, 3) (contiguous float32 CPU tables and points), added into ``into`` (two
    contiguous tensors shaped as the tables) or into zeros."""
    grad = grad.contiguous()
    g_plane, g_line = into if into is not None else (torch.zeros_like(plane), torch.zeros_like(line))
    threads = backward_threads(points.shape[0], plane.shape[0], torch.get_num_threads())
    _ext.backward(layout, plane.data_ptr(), line.data_ptr(), points.data_ptr(), points.shape[0],
                  grad.data_ptr(), g_plane.data_ptr(), g_line.data_ptr(), threads)
    return g_plane, g_line


# A backward worker past the first adds into a table-sized buffer of its own, summed at the
# end: it pays only when the points outnumber the rows that reduction touches. Measured on 2
# cores (docs/benchmarks.md, "Denormal numbers in the optimiser; threads in the compiled
# backward ..."): 20k points on a 512^3 colour table (786k rows) took 80 ms on 2 threads
# against 63 on one; 80k points, or 20k on a 256^3 table (197k rows), were faster on 2.
ROWS_PER_POINT_SERIAL = 16


def backward_threads(points: int, rows: int, threads: int) -> int:
    """Threads for a backward over ``points`` into tables of ``rows`` plane rows: one when
    the points are fewer than rows / ROWS_PER_POINT_SERIAL, else ``threads``."""
    return 1 if points * ROWS_PER_POINT_SERIAL < rows else max(1, threads)


def vm_lookup(plane: Tensor, line: Tensor, points: Tensor, layout: tuple[int, ...]) -> Tensor:
    """Features (P, 3 C), mode-major, at ``points`` (P, 3) in [-1, 1]; ``layout`` is
    (C, h0, w0, h1, w1, h2, w2, n0, n1, n2): the three planes' (height, width) and the three
    lines' lengths, stacked in that order in the (rows, C) tables ``plane`` and ``line``."""
    return _VMLookup.apply(plane, line, points, tuple(int(v) for v in layout))
