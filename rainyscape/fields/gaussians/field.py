"""GaussianField: 3D Gaussian Splatting behind the Field interface.

Parameters (one optimiser each, named as in gsplat): ``means``, ``scales`` (log),
``quats`` (w x y z), ``opacities`` (logit), ``sh0`` and ``shN`` (spherical harmonics up
to ``sh_degree``). Initialised from the scene's sparse points when it has them (COLMAP,
simulator depth), else at random (gsplat's: in a cube of 3 x the scene extent about the
cameras' centroid). The training schedule (SH degree, densification, position
learning-rate decay) is the 3DGS paper's 30k-step one, scaled to ``trainer.max_iters``
with floors in steps for short runs (:meth:`DensifySchedule.scaled`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import torch
from torch import Tensor, nn

from rainyscape.cameras import Cameras, Window, pixel_rays
from rainyscape.components import Callback, Field, ParamGroup, RenderOutput, TrainState
from rainyscape.config.schema import bounded
from rainyscape.errors import ConfigError
from rainyscape.fields.gaussians.densify import DefaultStrategy, DensifySchedule, Strategy
from rainyscape.fields.gaussians.mcmc import MCMCStrategy
from rainyscape.fields.gaussians.ply import write_ply
from rainyscape.fields.gaussians.rasterize import BACKENDS, rasterize
from rainyscape.fields.gaussians.sh import MAX_SH_DEGREE, num_sh_bases, rgb_to_sh0
from rainyscape.scene import SceneData

PARAM_NAMES = ("means", "scales", "quats", "opacities", "sh0", "shN")


def scene_extent(cameras: Cameras) -> float:
    """3DGS's scene scale: 1.1 x the largest camera distance from the cameras' centroid."""
    centers = cameras.centers.double()
    return float(1.1 * (centers - centers.mean(0)).norm(dim=-1).max().clamp_min(1e-6))


def growth_cap(max_gaussians: int, pixels_per_gaussian: int, train_pixels: int) -> int:
    """The most Gaussians densification may reach (0: no limit). A cap per training pixel
    keeps a 64 px scene from growing the Gaussians a 192 px one needs (and their cost)."""
    caps = [max_gaussians] if max_gaussians > 0 else []
    if pixels_per_gaussian > 0:
        caps.append(max(1, train_pixels // pixels_per_gaussian))
    return min(caps, default=0)


InitMode = Literal["auto", "points", "frustum", "random"]
StrategyName = Literal["default", "mcmc"]
MCMC_DEFAULT_CAP = 1_000_000  # gsplat's cap_max, for an MCMC run without a Gaussian cap


def init_mode(option: str, scene: SceneData) -> str:
    """What ``field.init`` starts from on ``scene``: ``auto`` is the scene's sparse points when
    it has them, else ``frustum`` for a forward-facing capture, else gsplat's ``random`` cube."""
    has_points = scene.points is not None and len(scene.points) > 0
    if option == "points" and not has_points:
        raise ConfigError(f"field.init=points: scene {scene.name} has no sparse points; "
                          "use field.init=auto, frustum or random")
    if option != "auto":
        return option
    return "points" if has_points else "frustum" if scene.forward_facing else "random"


def frustum_points(scene: SceneData, count: int, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    """``count`` points inside the training views' frustums and their colours: each on the ray
    of a random pixel of a random training view, at a z-depth uniform in disparity between the
    scene's near and far bounds, coloured by that pixel. A forward-facing capture (LLFF)
    without sparse points has its content there, not in a cube about its near-coincident
    cameras."""
    train = torch.tensor(scene.train_indices or list(range(scene.num_images)))
    view = train[torch.randint(len(train), (count,), generator=generator)]
    xs = torch.randint(scene.width, (count,), generator=generator)
    ys = torch.randint(scene.height, (count,), generator=generator)
    near, far = max(scene.near, 1e-3), max(scene.far, scene.near * 1.001, 2e-3)
    disparity = 1.0 / far + (1.0 / near - 1.0 / far) * torch.rand(count, generator=generator)
    rays = pixel_rays(scene.cameras[view], xs[:, None], ys[:, None])
    depth = (1.0 / disparity)[:, None] / rays.z_scale  # z-depth -> distance along the ray
    points = (rays.origins + rays.directions * depth[..., None])[:, 0].float()
    colors = scene.images[view, ys, xs].float() / 255.0
    return points, colors


def depth_guided_points(scene: SceneData, points: Tensor, count: int, generator: torch.Generator,
                        neighbours: int = 3) -> tuple[Tensor, Tensor]:
    """``count`` points on random pixels of random training views, each at the z-depth its
    nearest sparse points (in the image) have there (inverse-distance weighted), coloured by
    the pixel: a dense start where a sparse SfM model is thin (untextured walls, road), with
    depths from what the views themselves triangulated. Views that see fewer than
    ``neighbours`` points get none."""
    train = torch.tensor(scene.train_indices or list(range(scene.num_images)))
    per_view = torch.bincount(torch.randint(len(train), (count,), generator=generator), minlength=len(train))
    uv_all, z_all = scene.cameras[train].project(points.double().to(scene.cameras.c2w.dtype))
    out_p, out_c = [], []
    for i, v in enumerate(train.tolist()):
        n = int(per_view[i])
        uv, z = uv_all[i], z_all[i]
        seen = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < scene.width) & (uv[:, 1] >= 0) & (uv[:, 1] < scene.height)
        if n == 0 or int(seen.sum()) < neighbours:
            continue
        uv, z = uv[seen].float(), z[seen].float()
        xs = torch.randint(scene.width, (n,), generator=generator)
        ys = torch.randint(scene.height, (n,), generator=generator)
        pix = torch.stack([xs, ys], -1).float() + 0.5
        dist, idx = torch.cdist(pix, uv).topk(neighbours, largest=False)
        weight = 1.0 / dist.clamp_min(0.5)
        depth = (z[idx] * weight).sum(-1) / weight.sum(-1)
        rays = pixel_rays(scene.cameras[[v]], xs[None], ys[None])
        t = depth[None] / rays.z_scale  # z-depth -> distance along the ray
        out_p.append((rays.origins + rays.directions * t[..., None])[0].float())
        out_c.append(scene.images[v, ys, xs].float() / 255.0)
    if not out_p:
        return torch.zeros(0, 3), torch.zeros(0, 3)
    return torch.cat(out_p), torch.cat(out_c)


def nearest_neighbour_scale(points: Tensor, k: int = 3) -> Tensor:
    """Mean distance from each point to its k nearest others (3DGS's initial scale)."""
    from scipy.spatial import cKDTree

    pts = points.double().cpu().numpy()
    if len(pts) <= 1:
        return torch.full((len(pts),), 0.01)
    k = min(k, len(pts) - 1)
    dist, _ = cKDTree(pts).query(pts, k=k + 1)
    d = torch.from_numpy(dist[:, 1:]).float()
    return torch.sqrt((d ** 2).mean(-1)).clamp_min(1e-7)


class GaussianField(Field):
    """3D Gaussian Splatting (tiled torch rasteriser on CPU, gsplat on CUDA)."""

    description = "3D Gaussian Splatting: torch tiled rasteriser on CPU, gsplat on CUDA"

    @dataclass
    class Config:
        sh_degree: int = bounded(3, 0, MAX_SH_DEGREE)
        # auto: the scene's points if it has them, else frustum on forward-facing captures, else random
        init: InitMode = "auto"
        init_points: int = bounded(100_000, 0)  # at most this many of the scene's sparse points (random subset)
        # with sparse points: this many more on training pixels at the depth of their nearest
        # sparse points in the image (a dense start where SfM is thin; depth_guided_points)
        init_fill: int = bounded(0, 0, 10_000_000)
        random_points: int = bounded(100_000, 0)  # random Gaussians (gsplat: 100k) ...
        random_extent: float = bounded(3.0, 0.0)  # ... in a cube of this x the scene extent about the cameras' centroid (0: the scene box)
        init_opacity: float = bounded(0.1, hi=0.99, above=0.0)
        background: tuple[float, float, float] = bounded((0.0, 0.0, 0.0), 0.0, 1.0)
        backend: str = "auto"  # auto (gsplat on CUDA when installed) | torch | gsplat
        eps2d: float = bounded(0.3, 0.0)  # screen-space dilation (pixels^2) of every projected Gaussian
        near_plane: float = bounded(0.01, above=0.0)
        # Learning rates (3DGS); the means' lr is times the scene extent and decays to
        # lr_means_final over the run.
        lr_means: float = bounded(1.6e-4, 0.0)
        lr_means_final: float = bounded(1.6e-6, 0.0)
        lr_scales: float = bounded(5e-3, 0.0)
        lr_quats: float = bounded(1e-3, 0.0)
        lr_opacities: float = bounded(5e-2, 0.0)
        lr_sh0: float = bounded(2.5e-3, 0.0)
        lr_shN: float = bounded(2.5e-3 / 20, 0.0)
        # Schedule in steps of a reference_iters run, stretched to trainer.max_iters.
        reference_iters: int = bounded(30_000, 1)
        sh_degree_every: int = bounded(1000, 1)
        refine_start: int = bounded(500, 0)
        refine_stop: int = bounded(15_000, 0)
        refine_every: int = bounded(100, 1)
        min_refine_start: int = bounded(0, 0)  # first refinement after at least this many steps, whatever the run
        min_refine_every: int = bounded(0, 0)  # refinements at least this many steps apart, whatever the run
        reset_every: int = bounded(3000, 1)  # (a reset needs reset_every steps of densification after it)
        min_reset_every: int = bounded(1000, 0)  # opacity resets at least this many steps apart, whatever the run
        min_sh_degree_every: int = bounded(0, 0)  # one more SH degree at most every this many steps
        # default: 3DGS's clone / split / prune; mcmc: relocation and noise (3DGS-MCMC), count
        # capped from the start by max_gaussians / pixels_per_gaussian (else 1M)
        strategy: StrategyName = "default"
        mcmc_grow_rate: float = bounded(0.05, 0.0)  # mcmc: share more Gaussians per refinement, up to the cap
        mcmc_noise_lr: float = bounded(5e5, 0.0)  # mcmc: position noise, times the means' lr
        mcmc_min_opacity: float = bounded(0.005, 0.0, 1.0)  # mcmc: dead below this: relocated
        opacity_reg: float = bounded(0.01, 0.0)  # mcmc: L1 on opacities
        scale_reg: float = bounded(0.01, 0.0)  # mcmc: L1 on scales
        grow_grad2d: float = bounded(2e-4, 0.0)
        grow_scale3d: float = bounded(0.01, 0.0)
        prune_opacity: float = bounded(0.005, 0.0, 1.0)
        prune_scale3d: float = bounded(0.1, 0.0)
        max_gaussians: int = bounded(0, 0)  # growth stops at this many (0: no limit) ...
        pixels_per_gaussian: int = bounded(0, 0)  # ... or at training pixels / this, if fewer (0: off)
        # ... and, above 0, that cap reached only at this share of the densification window,
        # in proportion to the steps (densify.ramped_cap; 0: the whole cap from the start)
        cap_ramp: float = bounded(0.0, 0.0, 1.0)
        seed: int = 0  # initial subset / random Gaussians

    def __init__(self, config: "GaussianField.Config | None", scene: SceneData):
        super().__init__()
        self.config = c = config or self.Config()
        if not 0 <= c.sh_degree <= MAX_SH_DEGREE:
            raise ConfigError(f"field.sh_degree must be 0..{MAX_SH_DEGREE}, got {c.sh_degree}")
        if c.backend not in BACKENDS:
            raise ConfigError(f"field.backend must be one of {', '.join(BACKENDS)}, got '{c.backend}'")
        if len(c.background) != 3:
            raise ConfigError("field.background needs three values (r, g, b)")
        if c.init not in get_args(InitMode):
            raise ConfigError(f"field.init must be one of {', '.join(get_args(InitMode))}, got '{c.init}'")
        if c.strategy not in get_args(StrategyName):
            raise ConfigError(f"field.strategy must be one of {', '.join(get_args(StrategyName))}, got '{c.strategy}'")
        self.width, self.height = scene.width, scene.height
        train = scene.train_indices or list(range(scene.num_images))
        self.max_gaussians = growth_cap(c.max_gaussians, c.pixels_per_gaussian,
                                        len(train) * scene.width * scene.height)
        self.extent = scene_extent(scene.cameras[train])
        self.transform, self.world_scale = scene.transform.clone(), float(scene.scale)
        self.params = nn.ParameterDict(self._initial_params(scene))
        self.register_buffer("background", torch.tensor(c.background, dtype=torch.float32))
        self.register_buffer("active_sh_degree", torch.zeros((), dtype=torch.long))
        self._groups: dict[str, ParamGroup] = {}
        # Cumulative counts of the densifier's changes (logged through stats(); checkpointed
        # with the training callback).
        self.events = {"refinements": 0, "cloned": 0, "split": 0, "pruned": 0, "opacity_resets": 0}
        self.strategy = self._make_strategy()

    # ------------------------------------------------------------------ set-up

    def _initial_params(self, scene: SceneData) -> dict[str, nn.Parameter]:
        c = self.config
        gen = torch.Generator().manual_seed(c.seed)
        cap = self.max_gaussians or math.inf  # the growth cap bounds the start too
        init = init_mode(c.init, scene)
        if init == "points":
            points = scene.points.float()
            colors = (scene.point_colors.float() / 255.0 if scene.point_colors is not None
                      else torch.full_like(points, 0.5))
            keep = int(min(c.init_points, cap))
            if len(points) > keep:
                pick = torch.randperm(len(points), generator=gen)[:keep]
                points, colors = points[pick], colors[pick]
            fill = int(min(c.init_fill, max(cap - len(points), 0)))
            if fill > 0:
                more, more_colors = depth_guided_points(scene, points, fill, gen)
                points, colors = torch.cat([points, more]), torch.cat([colors, more_colors])
        elif init == "frustum":
            points, colors = frustum_points(scene, max(1, int(min(c.random_points, cap))), gen)
        else:
            count = max(1, int(min(c.random_points, cap)))
            if c.random_extent > 0:  # gsplat: a cube of init_extent x the scene scale
                train = scene.train_indices or list(range(scene.num_images))
                center = scene.cameras[train].centers.float().mean(0)
                half = c.random_extent * self.extent
                lo, hi = center - half, center + half
            else:
                lo, hi = scene.scene_box[0].float(), scene.scene_box[1].float()
            points = lo + (hi - lo) * torch.rand(count, 3, generator=gen)
            colors = torch.rand(count, 3, generator=gen)
        n = len(points)
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1.0
        return {
            "means": nn.Parameter(points),
            "scales": nn.Parameter(torch.log(nearest_neighbour_scale(points))[:, None].repeat(1, 3)),
            "quats": nn.Parameter(quats),
            "opacities": nn.Parameter(torch.full((n,), math.log(c.init_opacity / (1 - c.init_opacity)))),
            "sh0": nn.Parameter(rgb_to_sh0(colors)[:, None]),
            "shN": nn.Parameter(torch.zeros(n, num_sh_bases(c.sh_degree) - 1, 3)),
        }

    @property
    def num_gaussians(self) -> int:
        return self.params["means"].shape[0]

    def stats(self) -> dict[str, float]:
        """The Gaussian count, the SH degree in use and the densifier's cumulative changes."""
        return {"num_gaussians": self.num_gaussians, "sh_degree": int(self.active_sh_degree),
                **self.events}

    def param_groups(self) -> list[ParamGroup]:
        c = self.config
        lrs = {"means": c.lr_means * self.extent, "scales": c.lr_scales, "quats": c.lr_quats,
               "opacities": c.lr_opacities, "sh0": c.lr_sh0, "shN": c.lr_shN}
        self._groups = {name: ParamGroup(name, [self.params[name]], lr, eps=1e-15)
                        for name, lr in lrs.items()}
        # Exponential decay to lr_means_final over the whole run (lr_decay_steps 0: the run).
        self._groups["means"].lr_decay = c.lr_means_final / c.lr_means
        return list(self._groups.values())

    def sync_param_groups(self) -> None:
        """Point the ParamGroups handed to the trainer at the current tensors."""
        for name, group in self._groups.items():
            group.params = [self.params[name]]

    def callbacks(self) -> list[Callback]:
        return [GaussianTraining(self, self.strategy)]

    def _make_strategy(self) -> Strategy:
        c = self.config
        if c.strategy == "mcmc":
            return MCMCStrategy(self.schedule, self.max_gaussians or MCMC_DEFAULT_CAP, c.mcmc_min_opacity,
                                c.mcmc_grow_rate, c.mcmc_noise_lr, c.opacity_reg, c.scale_reg)
        return DefaultStrategy(self.schedule, c.grow_grad2d, c.grow_scale3d, c.prune_opacity,
                               c.prune_scale3d, self.max_gaussians, self.extent, c.cap_ramp)

    def extra_losses(self, output: RenderOutput, target: Tensor) -> dict[str, Tensor]:
        """The strategy's regularisers (MCMC: L1 on opacities and scales)."""
        return self.strategy.regularisation(self.params)

    def schedule(self, max_iters: int) -> DensifySchedule:
        c = self.config
        return DensifySchedule.scaled(max_iters, c.reference_iters, c.refine_start, c.refine_stop,
                                      c.refine_every, c.reset_every, c.sh_degree_every,
                                      c.min_reset_every, c.min_refine_every, c.min_refine_start,
                                      c.min_sh_degree_every)

    # ---------------------------------------------------------------- render

    def render(self, cameras: Cameras, window: Window) -> RenderOutput:
        p = self.params
        degree = min(int(self.active_sh_degree), self.config.sh_degree)
        # Only the active degree's coefficients; the rasteriser evaluates them in view only.
        coeffs = torch.cat([p["sh0"], p["shN"][:, :num_sh_bases(degree) - 1]], 1)
        viewmats, opacities = cameras.w2c(), torch.sigmoid(p["opacities"])
        out = rasterize(p["means"], p["quats"], p["scales"].exp(), opacities,
                        coeffs, viewmats, cameras.K(), self.width, self.height, window,
                        sh_degree=degree, backgrounds=self.background,
                        near_plane=self.config.near_plane, eps2d=self.config.eps2d,
                        backend=self.config.backend)
        if self.training and out.means2d.requires_grad:
            out.means2d.retain_grad()  # densification reads its gradient
        return RenderOutput(
            rgb=out.rgb.permute(0, 3, 1, 2), depth=out.depth.permute(0, 3, 1, 2),
            acc=out.alpha.permute(0, 3, 1, 2),
            extras={"means2d": out.means2d, "radii": out.radii,
                    "image_size": (self.width, self.height),
                    "window_size": (window.width, window.height),
                    # per Gaussian, for terms on the Gaussians themselves (losses/free_space.py):
                    # its opacity (with gradient) and its centre's z in each camera (C, N)
                    "opacities": opacities,
                    "centre_depths": (p["means"].detach() @ viewmats[:, 2, :3].T).T + viewmats[:, 2, 3:]})

    # ------------------------------------------------------------ persistence

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Accepts any number of Gaussians (densification changes it during training)."""
        for name in PARAM_NAMES:
            key = f"params.{name}"
            if key in state_dict and state_dict[key].shape != self.params[name].shape:
                self.params[name] = nn.Parameter(torch.empty_like(state_dict[key], device=self.params[name].device))
        result = super().load_state_dict(state_dict, strict=strict, assign=assign)
        self.sync_param_groups()
        return result

    @torch.no_grad()
    def export_ply(self, path: Path) -> None:
        """The standard 3DGS ``.ply``, in the input's world frame (undoes the dataparser's
        normalised = scale * (transform @ x))."""
        rot = self.transform[:3, :3]
        if not torch.allclose(rot, torch.eye(3), atol=1e-6):
            raise ConfigError("export_ply: the scene's normalisation rotates the world; rotating "
                              "spherical harmonics is not supported")
        p = {k: v.detach().cpu() for k, v in self.params.items()}
        means = p["means"] / self.world_scale - self.transform[:3, 3]
        write_ply(path, means, p["scales"] - math.log(self.world_scale), p["quats"],
                  p["opacities"], p["sh0"], p["shN"])


class GaussianTraining(Callback):
    """The 3DGS schedule: SH degree, and the densification strategy's changes."""

    def __init__(self, field: GaussianField, strategy: Strategy):
        self.field = field
        self.strategy = strategy
        self.last_stats: dict[str, int] = {}

    def before_step(self, state: TrainState) -> None:
        f = self.field
        f.active_sh_degree.fill_(f.schedule(state.max_iters).sh_degree_at(state.step, f.config.sh_degree))

    def after_backward(self, state: TrainState, output: RenderOutput) -> None:
        self.strategy.observe(state, output)

    def after_step(self, state: TrainState) -> None:
        events = self.strategy.refine(state, self.field.params)
        if not events:
            return
        for key, n in events.items():
            self.field.events[key] = self.field.events.get(key, 0) + n
        self.last_stats = {**events, "gaussians": self.field.num_gaussians}
        self.field.sync_param_groups()

    def state_dict(self) -> dict:
        return {**self.strategy.state_dict(), "events": dict(self.field.events)}

    def load_state_dict(self, state: dict) -> None:
        self.strategy.load_state_dict(state)
        self.field.events.update(state.get("events", {}))
