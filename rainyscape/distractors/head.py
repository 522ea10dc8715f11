"""DeSplat's per-view distractor Gaussians (Wang et al., CVPR 2025) as an image-layer head.

Each training view owns a set of Gaussians that only it sees: they start as DeSplat's 1000
Gaussians per 504 x 378 px view, as a density (86 at 128 px: 1000 on a 128 px view let the
layer copy the whole view, 1.6 dB lower on crossroad-traffic), spread over the view's
frustum a short way in front of its camera (``init_depth`` x the scene extent; DeSplat:
0.02 of its normalised scene),
with plain RGB colours (no view dependence), opacity 0.1, the 3-nearest-neighbour scale
and random rotations. For (view, window) the head rasterises that view's set alone into a
premultiplied colour D and a coverage alpha_D: a (B, 4, h, w) layer laid over the scene's
render B as D + (1 - alpha_D) B (:meth:`composite`). Distractors (things in one view only)
are cheaper to explain there than in the shared 3D Gaussians, so they end up in this layer;
evaluation renders the field alone: the static scene.

The head renders with the Gaussian field's public rasteriser
(:func:`rainyscape.fields.gaussians.rasterize.rasterize`) and changes its parameter set with
the field's parameter surgery (``ops``); its densification (:mod:`.densify`) is DeSplat's
per-view adaptive density control. Learning rates are DeSplat's (the means' times the scene
extent, as the field's). Settings follow the authors' public code (AaltoML/desplat); no code
is taken from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from rainyscape.cameras import Cameras, Window, pixel_rays
from rainyscape.components import Callback, ImageHead, ParamGroup
from rainyscape.config.schema import bounded
from rainyscape.distractors.densify import DistractorDensify
from rainyscape.errors import ConfigError
from rainyscape.fields.gaussians.field import nearest_neighbour_scale, scene_extent
from rainyscape.fields.gaussians.rasterize import BACKENDS, Rasterized, rasterize
from rainyscape.imaging.compositing import over
from rainyscape.scene import SceneData

ATTRIBUTES = ("means", "scales", "quats", "opacities", "colors")


def random_quats(n: int, generator: torch.Generator) -> Tensor:
    """Uniformly random unit quaternions (N, 4) (Shoemake's method)."""
    u1, u2, u3 = torch.rand(3, n, generator=generator)
    a, b = torch.sqrt(1 - u1), torch.sqrt(u1)
    t2, t3 = 2 * torch.pi * u2, 2 * torch.pi * u3
    return torch.stack([a * torch.sin(t2), a * torch.cos(t2), b * torch.sin(t3), b * torch.cos(t3)], -1)


def frustum_slice(cameras: Cameras, index: int, count: int, depth: float,
                  generator: torch.Generator) -> Tensor:
    """``count`` world points (N, 3) at z-depth ``depth`` in front of camera ``index``, under
    pixels drawn uniformly over its image."""
    cam = cameras[[index]]
    # pixel_rays takes pixel indices (their centres at + 0.5): uniform over the image
    xs = torch.rand(1, count, generator=generator) * cameras.width - 0.5
    ys = torch.rand(1, count, generator=generator) * cameras.height - 0.5
    rays = pixel_rays(cam, xs, ys)
    distance = depth / rays.z_scale  # z-depth -> distance along each ray
    return (rays.origins + rays.directions * distance[..., None])[0].float()


class DistractorGaussians(ImageHead):
    """DeSplat: per-view distractor Gaussians, a (colour, alpha) layer over the render."""

    description = "DeSplat: per-view distractor Gaussians, laid over the render as (colour, alpha)"
    layer = "distractor"

    @dataclass
    class Config:
        # initial Gaussians of a training view: DeSplat's 1000 on its images (RobustNeRF's and
        # On-the-go's at 1/8 scale, 504 x 378 px) as a density, so a view gets 1000 x its
        # pixels / reference_pixels (86 at 128 x 128 px; reference_pixels 0: 1000 whatever the size)
        gaussians_per_view: int = bounded(1000, 1)
        reference_pixels: int = bounded(504 * 378, 0)
        init_depth: float = bounded(0.02, above=0.0)  # x the scene extent, in front of the camera
        init_opacity: float = bounded(0.1, hi=0.99, above=0.0)
        lr_means: float = bounded(1.6e-4, 0.0)  # x the scene extent, decaying to lr_means_final
        lr_means_final: float = bounded(1.6e-6, 0.0)
        lr_colors: float = bounded(0.025, 0.0)
        lr_opacities: float = bounded(0.05, 0.0)
        lr_scales: float = bounded(0.05, 0.0)
        lr_quats: float = bounded(0.01, 0.0)
        # per-view adaptive density control (densify.py): every refine_every_views passes
        # over the training views (each view seen about that many times) ...
        refine_every_views: int = bounded(10, 1)
        refine_stop: float = bounded(0.5, 0.0, 1.0)  # ... until this share of the run
        # clone above this mean 2D-gradient norm: of the absolute gradient (AbsGS), as
        # DeSplat's splatfacto, at its 0.0008 (absgrad=false: the net gradient, as 3DGS,
        # whose threshold is 0.0002) ...
        absgrad: bool = True
        grow_grad2d: float = bounded(8e-4, 0.0)
        split_screen: float = bounded(0.05, 0.0)  # ... split above this radius / image size
        cull_opacity: float = bounded(0.1, 0.0, 1.0)  # remove below this opacity, and unseen ones
        max_per_view: int = bounded(0, 0)  # at most this many per view (0: no limit)
        near_plane: float = bounded(0.001, above=0.0)  # the distractors sit close to the camera
        eps2d: float = bounded(0.3, 0.0)
        backend: str = "auto"  # auto | torch | gsplat (as the field's)
        seed: int = 0

    def __init__(self, config: "DistractorGaussians.Config | None", scene: SceneData):
        super().__init__()
        self.config = c = config or self.Config()
        if c.backend not in BACKENDS:
            raise ConfigError(f"rain_head.backend must be one of {', '.join(BACKENDS)}, got '{c.backend}'")
        self.width, self.height = scene.width, scene.height
        train = list(scene.train_indices or range(scene.num_images))
        self.views = train
        self.extent = scene_extent(scene.cameras[train])
        self.register_buffer("viewmats", scene.cameras.w2c().float(), persistent=False)
        self.register_buffer("Ks", scene.cameras.K().float(), persistent=False)
        gen = torch.Generator().manual_seed(c.seed)
        self.sets = nn.ModuleDict({str(v): self._initial_set(scene.cameras, v, gen) for v in train})
        self._groups: dict[str, ParamGroup] = {}
        self.last: list[tuple[int, Rasterized, tuple[int, int]]] = []  # this step's renders (training)
        self.densify = DistractorDensify(self)

    def initial_count(self) -> int:
        """Distractor Gaussians a view starts with (its share of DeSplat's density)."""
        c = self.config
        if c.reference_pixels <= 0:
            return c.gaussians_per_view
        return max(1, round(c.gaussians_per_view * self.width * self.height / c.reference_pixels))

    def _initial_set(self, cameras: Cameras, view: int, gen: torch.Generator) -> nn.ParameterDict:
        c = self.config
        n = self.initial_count()
        means = frustum_slice(cameras, view, n, c.init_depth * self.extent, gen)
        logit = torch.logit(torch.tensor(c.init_opacity)).item()
        return nn.ParameterDict({
            "means": nn.Parameter(means),
            "scales": nn.Parameter(torch.log(nearest_neighbour_scale(means))[:, None].repeat(1, 3)),
            "quats": nn.Parameter(random_quats(n, gen)),
            "opacities": nn.Parameter(torch.full((n,), logit)),
            "colors": nn.Parameter(torch.rand(n, 3, generator=gen)),
        })

    # ------------------------------------------------------------------ interface

    def params_of(self, view: int) -> nn.ParameterDict:
        return self.sets[str(view)]

    def counts(self) -> dict[int, int]:
        """Distractor Gaussians per training view."""
        return {v: int(self.sets[str(v)]["means"].shape[0]) for v in self.views}

    def stats(self) -> dict[str, float]:
        """Distractor Gaussians over all views and per view, and the density control's counts."""
        counts = self.counts().values()
        return {"num_gaussians": sum(counts), "per_view": sum(counts) / max(len(counts), 1),
                **{k: float(v) for k, v in self.densify.events.items()}}

    def param_groups(self) -> list[ParamGroup]:
        c = self.config
        lrs = {"means": c.lr_means * self.extent, "scales": c.lr_scales, "quats": c.lr_quats,
               "opacities": c.lr_opacities, "colors": c.lr_colors}
        self._groups = {a: ParamGroup(f"distractor_{a}", [self.sets[str(v)][a] for v in self.views], lr, eps=1e-15)
                        for a, lr in lrs.items()}
        self._groups["means"].lr_decay = c.lr_means_final / c.lr_means if c.lr_means > 0 else 1.0
        return list(self._groups.values())

    def group_name(self, attribute: str) -> str:
        return f"distractor_{attribute}"

    def sync_param_groups(self) -> None:
        """Point the ParamGroups handed to the trainer at the current tensors."""
        for a, group in self._groups.items():
            group.params = [self.sets[str(v)][a] for v in self.views]

    def callbacks(self) -> list[Callback]:
        return [self.densify]

    def composite(self, below: Tensor, layer: Tensor) -> Tensor:
        return over(layer, below)

    def render_view(self, view: int, window: Window, index: int) -> Rasterized:
        """Rasterise ``view``'s distractor Gaussians in the ``index``-th window of ``window``."""
        p = self.sets[str(view)]
        win = Window(window.x0[index:index + 1], window.y0[index:index + 1], window.width, window.height)
        return rasterize(p["means"], p["quats"], p["scales"].exp(), torch.sigmoid(p["opacities"]),
                         p["colors"].clamp(0.0, 1.0), self.viewmats[view:view + 1], self.Ks[view:view + 1],
                         self.width, self.height, win, near_plane=self.config.near_plane,
                         eps2d=self.config.eps2d, backend=self.config.backend,
                         absgrad=self.config.absgrad)

    def forward(self, view_ids: Tensor, window: Window) -> Tensor:
        layers = []
        self.last = []
        for b, v in enumerate(view_ids.tolist()):
            if str(v) not in self.sets:  # a view without distractors (held out): an empty layer
                layers.append(torch.zeros(1, 4, window.height, window.width, device=self.viewmats.device))
                continue
            out = self.render_view(v, window, b)
            if self.training and out.means2d.requires_grad:
                out.means2d.retain_grad()  # densification reads its gradient
                self.last.append((v, out, (window.width, window.height)))
            layers.append(torch.cat([out.rgb, out.alpha], -1).permute(0, 3, 1, 2))
        return torch.cat(layers, 0)

    # ------------------------------------------------------------ persistence

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Accepts any number of Gaussians per view (densification changes it)."""
        for v in self.views:
            for a in ATTRIBUTES:
                key = f"sets.{v}.{a}"
                p = self.sets[str(v)][a]
                if key in state_dict and state_dict[key].shape != p.shape:
                    self.sets[str(v)][a] = nn.Parameter(torch.empty_like(state_dict[key], device=p.device))
        result = super().load_state_dict(state_dict, strict=strict, assign=assign)
        self.sync_param_groups()
        return result
