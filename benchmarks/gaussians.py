"""Speed of the Gaussian field: CPU training steps and evaluation renders, against a naive
dense torch compositor, and gsplat vs the torch path where CUDA is present.

    python benchmarks/gaussians.py speed [--sizes 10000,50000,200000] [--repeats 3]
                                         [--dense-evals 7e8] [--threads 2]
    python benchmarks/gaussians.py gpu   [--sizes 10000,50000,200000]   (CUDA + gsplat: gsplat
                                         on the GPU vs the torch path on the CPU, same scene)

The scene: N random Gaussians filling a 2.4 x 2.4 x 1 slab 4 units in front of one
256 x 256 camera (f = 300 px), sized ~1/sqrt(N) so the image stays covered as N grows
(like a trained scene: more Gaussians, smaller ones), SH degree 3. A training step is
render + L1 loss + backward + Adam on the six parameter groups, through GaussianField
exactly as training runs it; "patch" is a 64 x 64 window, "full" the whole image.
Times are medians over ``--repeats`` runs, wall clock and process CPU time (all threads).
The dense step (where Gaussians x pixels <= ``--dense-evals``; timed once, it is slow) is
the same projection composited by the brute-force reference (every pixel against every
Gaussian, plain autograd), back-propagated one pixel chunk at a time so its memory stays
bounded; it leaves out SH and Adam, so its ratio to our full step understates the gain.
Quality is measured with rs-bench (see docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from rainyscape.cameras import Cameras, Window
from rainyscape.fields.gaussians.field import GaussianField
from rainyscape.fields.gaussians.projection import project_gaussians
from rainyscape.fields.gaussians.rasterize import rasterize
from rainyscape.testing.reference_rasterizer import composite_pixels
from rainyscape.scene import SceneData

SIZE = 256
PATCH = Window(torch.tensor([96]), torch.tensor([96]), 64, 64)


def make_field(n: int, device: torch.device, seed: int = 0) -> GaussianField:
    """A GaussianField over a synthetic one-camera scene with ``n`` random Gaussians."""
    g = torch.Generator().manual_seed(seed)
    points = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([2.4, 2.4, 1.0])
    points[:, 2] += 4.0
    cams = Cameras(torch.eye(4)[None], torch.tensor([300.0]), torch.tensor([300.0]),
                   torch.tensor([SIZE / 2]), torch.tensor([SIZE / 2]), SIZE, SIZE)
    scene = SceneData(
        name="bench", images=torch.zeros(1, SIZE, SIZE, 3, dtype=torch.uint8), cameras=cams,
        image_names=["0.png"], train_indices=[0], eval_indices=[], near=2.0, far=6.0,
        scene_box=torch.tensor([[-1.2, -1.2, 3.5], [1.2, 1.2, 4.5]]), points=points,
        point_colors=torch.randint(0, 256, (n, 3), generator=g, dtype=torch.uint8))
    field = GaussianField(GaussianField.Config(init_points=n, init_opacity=0.5), scene)
    with torch.no_grad():  # random orientations, anisotropic, ~1/sqrt(n) in size
        s = 1.8 / n ** 0.5
        field.params["scales"].copy_(torch.log(torch.rand(n, 3, generator=g) * s + 0.2 * s))
        field.params["quats"].copy_(torch.randn(n, 4, generator=g))
        field.params["opacities"].uniform_(-1.5, 2.0, generator=g)
        field.params["shN"].normal_(0, 0.1, generator=g)
    field.active_sh_degree.fill_(3)
    return field.to(device), cams.to(device)


def timed(fn, repeats: int, sync) -> tuple[float, float]:
    """Median wall and CPU seconds of ``fn()`` (after one warm-up call)."""
    fn()
    sync()
    walls, cpus = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        fn()
        sync()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return statistics.median(walls), statistics.median(cpus)


def train_step_fn(field: GaussianField, cams: Cameras, window: Window):
    opts = {g.name: torch.optim.Adam(g.params, lr=g.lr, eps=g.eps) for g in field.param_groups()}
    target = torch.rand(1, 3, window.height, window.width, device=cams.device)

    def step():
        field.train()
        out = field.render(cams, window)
        loss = (out.rgb - target).abs().mean()
        for o in opts.values():
            o.zero_grad(set_to_none=True)
        loss.backward()
        for o in opts.values():
            o.step()

    return step


def dense_step_fn(field: GaussianField, cams: Cameras, window: Window):
    """The same projection, composited by the naive all-pixels x all-Gaussians reference
    (plain autograd). Memory stays bounded: each pixel chunk is composited and
    back-propagated on its own into the projection's outputs, which are then
    back-propagated once through the projection."""
    p = field.params
    ii, jj = torch.meshgrid(torch.arange(window.height), torch.arange(window.width), indexing="ij")
    px, py = jj.reshape(-1) + 0.5, ii.reshape(-1) + 0.5

    def step():
        proj = project_gaussians(p["means"], p["quats"], p["scales"].exp(),
                                 torch.sigmoid(p["opacities"]), cams.w2c(), cams.K(), SIZE, SIZE,
                                 window.x0, window.y0, window.width, window.height)
        order = torch.argsort(proj.depths[0].detach(), stable=True)  # all are in front
        feats = torch.cat([torch.sigmoid(p["sh0"][:, 0]), proj.depths[0, :, None]], -1)
        outputs = [proj.means2d[0], proj.conics[0], proj.opacities[0], feats]
        leaves = [t.detach()[order].requires_grad_(True) for t in outputs]
        chunk = max(16, (1 << 24) // max(len(order), 1))  # ~64 MB per (N, pixels) array
        for x, y in zip(px.split(chunk), py.split(chunk)):
            out, alpha = composite_pixels(*leaves, x, y)
            ((out.sum() + alpha.sum()) / len(px)).backward()
        grads = [torch.empty_like(t).index_copy_(0, order, leaf.grad)
                 for t, leaf in zip(outputs, leaves)]
        torch.autograd.backward(outputs, grads)
        for q in p.values():
            q.grad = None

    return step


def speed(args) -> None:
    torch.set_num_threads(args.threads)
    dev = torch.device("cpu")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {SIZE}x{SIZE} image")
    print("| Gaussians | what | wall ms | CPU ms | dense wall ms | dense / ours |")
    print("|---|---|---|---|---|---|")
    for n in args.sizes:
        field, cams = make_field(n, dev)
        for name, window in (("train step, 64x64 patch", PATCH),
                             ("train step, full image", Window.full(cams))):
            wall, cpu = timed(train_step_fn(field, cams, window), args.repeats, lambda: None)
            dense = ""
            ratio = ""
            if n * window.width * window.height <= args.dense_evals:
                d_wall, _ = timed(dense_step_fn(field, cams, window), 1, lambda: None)
                dense, ratio = f"{d_wall * 1e3:.0f}", f"{d_wall / wall:.1f}x"
            print(f"| {n} | {name} | {wall * 1e3:.0f} | {cpu * 1e3:.0f} | {dense} | {ratio} |", flush=True)
        field.eval()

        def render():
            with torch.no_grad():
                field.render(cams, Window.full(cams))

        wall, cpu = timed(render, args.repeats, lambda: None)
        print(f"| {n} | eval render, full image | {wall * 1e3:.0f} | {cpu * 1e3:.0f} | | "
              f"{1 / wall:.1f} images/s |", flush=True)


def gpu(args) -> None:
    """gsplat on the GPU against our torch path on the CPU, for the same scene."""
    from rainyscape.fields.gaussians.rasterize_gsplat import gsplat_installed

    if not (torch.cuda.is_available() and gsplat_installed()):
        raise SystemExit("gpu: needs CUDA and gsplat (pip install 'rainyscape[cuda]')")
    torch.set_num_threads(args.threads)
    print(f"{torch.cuda.get_device_name()}; torch path on the CPU with {args.threads} threads")
    print("| Gaussians | fwd + bwd | gsplat (GPU) ms | torch (CPU) ms | max abs diff | mean abs diff |")
    print("|---|---|---|---|---|---|")
    devices = {"gsplat": torch.device("cuda"), "torch": torch.device("cpu")}
    syncs = {"gsplat": torch.cuda.synchronize, "torch": lambda: None}
    for n in args.sizes:
        fields = {k: make_field(n, d) for k, d in devices.items()}
        for name, window in (("64x64 patch", PATCH), ("full image", None)):
            outs, times = {}, {}
            for backend, (field, cams) in fields.items():
                p = field.params
                win = window or Window.full(cams)

                def step(p=p, cams=cams, win=win, backend=backend):
                    out = rasterize(p["means"], p["quats"], p["scales"].exp(),
                                    torch.sigmoid(p["opacities"]), torch.sigmoid(p["sh0"][:, 0]),
                                    cams.w2c(), cams.K(), SIZE, SIZE, win, backend=backend)
                    outs[backend] = out.rgb.detach().cpu()
                    out.rgb.mean().backward()

                times[backend], _ = timed(step, args.repeats, syncs[backend])
            diff = (outs["gsplat"] - outs["torch"]).abs()
            print(f"| {n} | {name} | {times['gsplat'] * 1e3:.2f} | {times['torch'] * 1e3:.0f} | "
                  f"{float(diff.max()):.2e} | {float(diff.mean()):.2e} |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["speed", "gpu"])
    ap.add_argument("--sizes", default="10000,50000,200000",
                    type=lambda s: [int(x) for x in s.split(",")])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--dense-evals", type=float, default=7e8,
                    help="run the dense reference where Gaussians x pixels is at most this")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    (speed if args.what == "speed" else gpu)(args)


if __name__ == "__main__":
    main()
