"""Speed of the CPU rasterisers (torch and the compiled cpp kernel) on realistic Gaussian
sets: one 240 x 180 view (and a 240 x 135 one), 20k / 50k / 100k Gaussians.

    OMP_NUM_THREADS=1 python benchmarks/rasterizer.py [--sizes 20000,50000,100000]
        [--scenes trained,sfm,mix] [--views 240x180,240x135] [--backends torch,cpp]
        [--repeats 5] [--threads 1] [--json FILE]
    OMP_NUM_THREADS=1 python benchmarks/rasterizer.py --profile sfm --sizes 20000
        (torch.profiler table of one torch-path step on that scene)

Against an earlier version of the torch rasteriser (a copy of its package, e.g.
``git archive 096cb98 rainyscape | tar -x -C /tmp/base``): run it there with
``--package /tmp/base --backends torch --json base.json``, then here with
``--baseline base.json``: an extra column gives that run's torch time / this run's cpp
time (two processes: compare under the same machine load).

One timed step is ``rasterize()`` forward (cull, projection, compositing of rgb + depth)
and backward of loss = sum(rgb * fixed random weights), with gradients for means, quats,
scales, opacities and colours: what a training step pays for rendering a whole view.
Medians over ``--repeats`` steps after one warm-up, wall clock and process CPU time
(user + sys of all threads); both backends run in the same process, scene by scene, so
their ratio is taken under the same machine load.

The Gaussian sets, all in the frustum of one pinhole camera (f = 200 px for 240 px,
depths 2 to 8):
- ``trained``: what a trained scene holds: small anisotropic Gaussians, a few pixels
  (screen-space sigma log-normal around 1.5 px), half of them nearly opaque.
- ``sfm``: a run started from a sparse point cloud: 2,000 sparse points; each Gaussian
  sits near one of them (as clones / splits of it) with the 3DGS initial scale, the RMS
  distance from that point to its 3 nearest sparse neighbours (isotropic, tens of pixels
  wide), and the initial opacity 0.1: large, overlapping, semi-transparent.
- ``mix``: 85 % trained-like, 14 % sfm-like, 1 % very large ones (3x the sfm scale,
  opacity 0.05 to 0.9).
The pairs column counts Gaussian-tile intersections of the torch path's 16 x 16 binning
(bounding boxes) and, for cpp, of its exact ellipse-tile test.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time

import sys

import torch

FOCAL_PER_WIDTH = 200.0 / 240.0
SPARSE_POINTS = 2000


def camera(width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    f = FOCAL_PER_WIDTH * width
    ks = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])[None]
    return torch.eye(4)[None], ks


def frustum_points(n: int, width: int, height: int, g: torch.Generator) -> torch.Tensor:
    """Points whose projections cover the view (10 % margin), depths log-uniform in [2, 8]."""
    f = FOCAL_PER_WIDTH * width
    u = (torch.rand(n, generator=g) * 1.2 - 0.1) * width - width / 2
    v = (torch.rand(n, generator=g) * 1.2 - 0.1) * height - height / 2
    z = 2.0 * 4.0 ** torch.rand(n, generator=g)
    return torch.stack([u * z / f, v * z / f, z], -1)


def knn_rms(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """RMS distance of each point to its k nearest others (the 3DGS initial scale)."""
    d2 = torch.cdist(points, points).square_()
    d2.fill_diagonal_(float("inf"))
    return d2.topk(k, largest=False).values.mean(-1).sqrt()


def trained_like(n: int, width: int, height: int, g: torch.Generator):
    f = FOCAL_PER_WIDTH * width
    means = frustum_points(n, width, height, g)
    px = torch.exp(torch.randn(n, generator=g) * 0.5 + math.log(1.5))  # screen sigma, px
    scales = (px * means[:, 2] / f)[:, None] * (torch.rand(n, 3, generator=g) * 1.2 + 0.3)
    opac = torch.where(torch.rand(n, generator=g) < 0.5,
                       torch.rand(n, generator=g) * 0.3 + 0.7,
                       torch.rand(n, generator=g) * 0.65 + 0.05)
    return means, scales, opac


def sfm_like(n: int, width: int, height: int, g: torch.Generator, sparse: torch.Tensor,
             sparse_scale: torch.Tensor):
    parent = torch.randint(0, len(sparse), (n,), generator=g)
    scale = sparse_scale[parent]
    means = sparse[parent] + torch.randn(n, 3, generator=g) * 0.3 * scale[:, None]
    return means, scale[:, None].expand(n, 3).clone(), torch.full((n,), 0.1)


def make_scene(kind: str, n: int, width: int, height: int, seed: int = 0):
    """means, quats, scales, opacities, colours of one Gaussian set (see the docstring)."""
    g = torch.Generator().manual_seed(seed)
    sparse = frustum_points(SPARSE_POINTS, width, height, g)
    sparse_scale = knn_rms(sparse)
    if kind == "trained":
        means, scales, opac = trained_like(n, width, height, g)
    elif kind == "sfm":
        means, scales, opac = sfm_like(n, width, height, g, sparse, sparse_scale)
    elif kind == "mix":
        n_big = max(1, n // 100)
        n_sfm = int(0.14 * n)
        parts = [trained_like(n - n_sfm - n_big, width, height, g),
                 sfm_like(n_sfm, width, height, g, sparse, sparse_scale)]
        m, s, _ = sfm_like(n_big, width, height, g, sparse, sparse_scale)
        parts.append((m, s * 3.0, torch.rand(n_big, generator=g) * 0.85 + 0.05))
        means, scales, opac = (torch.cat(t) for t in zip(*parts))
    else:
        raise SystemExit(f"--scenes: unknown scene '{kind}' (trained, sfm, mix)")
    quats = torch.randn(n, 4, generator=g)
    colors = torch.rand(n, 3, generator=g)
    return [means, quats, scales, opac, colors]


def pairs_count(params, viewmats, ks, width: int, height: int) -> int:
    """Gaussian-tile intersections of the torch path's 16 x 16 binning."""
    from rainyscape.fields.gaussians.projection import candidate_gaussians, project_gaussians
    from rainyscape.fields.gaussians.rasterize_torch import bin_gaussians

    with torch.no_grad():
        means, quats, scales, opac, _ = params
        ids = candidate_gaussians(means, scales, opac, viewmats, ks, width, height,
                                  torch.zeros(1), torch.zeros(1), width, height)
        proj = project_gaussians(means[ids], quats[ids], scales[ids], opac[ids], viewmats, ks,
                                 width, height)
        return len(bin_gaussians(proj, width, height).gaussian_ids)


def cpp_pairs(params, viewmats, ks, width: int, height: int) -> int | None:
    from rainyscape.fields.gaussians.projection import project_gaussians
    try:
        from rainyscape.fields.gaussians.rasterize_cpp import binning_pairs, cpp_available
    except ImportError:  # an earlier version of the package
        return None
    if not cpp_available():
        return None
    with torch.no_grad():
        means, quats, scales, opac, _ = params
        proj = project_gaussians(means, quats, scales, opac, viewmats, ks, width, height)
        return binning_pairs(proj, width, height)


def step(params, weights, viewmats, ks, width: int, height: int, backend: str) -> None:
    from rainyscape.fields.gaussians.rasterize import rasterize

    leaves = [p.detach().requires_grad_(True) for p in params]
    out = rasterize(*leaves, viewmats, ks, width, height, backend=backend)
    (out.rgb * weights).sum().backward()


def time_steps(fn, repeats: int) -> tuple[float, float]:
    """Median wall and CPU seconds of ``fn()`` over ``repeats`` calls after one warm-up."""
    fn()
    walls, cpus = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus)


def profile(kind: str, n: int, width: int, height: int) -> None:
    from torch.profiler import ProfilerActivity, profile as torch_profile

    params = make_scene(kind, n, width, height)
    viewmats, ks = camera(width, height)
    weights = torch.rand(1, height, width, 3, generator=torch.Generator().manual_seed(1))
    step(params, weights, viewmats, ks, width, height, "torch")
    with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
        step(params, weights, viewmats, ks, width, height, "torch")
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="20000,50000,100000")
    parser.add_argument("--scenes", default="trained,sfm,mix")
    parser.add_argument("--views", default="240x180,240x135")
    parser.add_argument("--backends", default="torch,cpp")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--profile", default="", help="profile the torch path on this scene")
    parser.add_argument("--json", default="", help="also write the rows to this file")
    parser.add_argument("--package", default="",
                        help="import rainyscape from this folder (an earlier version)")
    parser.add_argument("--baseline", default="",
                        help="JSON of an earlier run: add its torch time / this cpp time")
    args = parser.parse_args()
    if args.package:  # ahead of the editable install's import hook
        sys.meta_path = [f for f in sys.meta_path if "editable" not in repr(f).lower()]
        sys.path.insert(0, args.package)
    baseline = {}
    if args.baseline:
        with open(args.baseline) as fh:
            baseline = {(r["view"], r["scene"], r["n"]): r["torch"]["cpu_ms"]
                        for r in json.load(fh)["rows"]}
    torch.set_num_threads(args.threads)
    sizes = [int(s) for s in args.sizes.split(",")]
    views = [tuple(int(v) for v in view.split("x")) for view in args.views.split(",")]
    if args.profile:
        profile(args.profile, sizes[0], *views[0])
        return
    backends = args.backends.split(",")
    rows = []
    print(f"threads {args.threads}, repeats {args.repeats}; times: median wall / CPU ms")
    header = "view     scene    N       pairs16  pairs_cpp " + " ".join(
        f"{b + ' wall':>11} {b + ' cpu':>10}" for b in backends)
    print(header + ("  torch/cpp" if {"torch", "cpp"} <= set(backends) else "")
          + ("  baseline/cpp" if baseline and "cpp" in backends else ""))
    for width, height in views:
        viewmats, ks = camera(width, height)
        weights = torch.rand(1, height, width, 3, generator=torch.Generator().manual_seed(1))
        for kind in args.scenes.split(","):
            for n in sizes:
                params = make_scene(kind, n, width, height)
                row = {"view": f"{width}x{height}", "scene": kind, "n": n,
                       "pairs16": pairs_count(params, viewmats, ks, width, height),
                       "pairs_cpp": cpp_pairs(params, viewmats, ks, width, height)}
                for b in backends:
                    wall, cpu = time_steps(
                        lambda: step(params, weights, viewmats, ks, width, height, b),
                        args.repeats)
                    row[b] = {"wall_ms": 1e3 * wall, "cpu_ms": 1e3 * cpu}
                line = (f"{row['view']:8} {kind:8} {n:<7} {row['pairs16']:<8} "
                        f"{str(row['pairs_cpp']):<9} " + " ".join(
                            f"{row[b]['wall_ms']:11.1f} {row[b]['cpu_ms']:10.1f}"
                            for b in backends))
                if "torch" in row and "cpp" in row:
                    row["torch_over_cpp_cpu"] = row["torch"]["cpu_ms"] / row["cpp"]["cpu_ms"]
                    line += f"  {row['torch_over_cpp_cpu']:8.1f}x"
                key = (row["view"], kind, n)
                if "cpp" in row and key in baseline:
                    row["baseline_torch_cpu_ms"] = baseline[key]
                    row["baseline_over_cpp_cpu"] = baseline[key] / row["cpp"]["cpu_ms"]
                    line += f"  {row['baseline_over_cpp_cpu']:10.1f}x"
                print(line, flush=True)
                rows.append(row)
    for b in backends:  # cost of the large-Gaussian sets relative to the trained-like ones
        for view in {r["view"] for r in rows}:
            for n in sizes:
                by = {r["scene"]: r[b]["cpu_ms"] for r in rows if r["view"] == view and r["n"] == n}
                if "trained" in by:
                    ratios = ", ".join(f"{k}/trained {v / by['trained']:.2f}"
                                       for k, v in by.items() if k != "trained")
                    print(f"{b:6} {view} N={n}: {ratios}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"threads": args.threads, "repeats": args.repeats, "rows": rows}, fh,
                      indent=1)


if __name__ == "__main__":
    main()
