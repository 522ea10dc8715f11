"""``packed-grid``: a NeRF field of factorised feature grids (TensoRF VM by default, K-Planes,
hash), a tiny colour MLP, an EMA occupancy grid for empty-space skipping, packed samples,
coarse-to-fine growth. An option (``field=packed-grid``): at the ``nerf`` CPU recipe's time
it measured below the ``grid`` field on the cpu set (docs/benchmarks.md, "Packed-grid field
vs grid field"), so ``nerf`` keeps ``grid``.

- **Space** (:mod:`.space`): the scene box is the grid cube for bounded scenes (``box``), its
  inner part for unbounded ones (``contract``: the rest of space goes to the shell), and NDC
  for forward-facing captures (``ndc``); ``auto`` picks ``ndc`` for forward-facing scenes
  and ``contract`` otherwise.
- **Features** (:mod:`.grid_encodings`): ``vm`` (TensoRF), ``planes`` (K-Planes), ``hash``
  (Instant-NGP), each giving a raw density and appearance features; sigma =
  ``density_scale`` softplus(raw + ``density_shift``) and a one-hidden-layer MLP of the features
  and the encoded view direction gives the colour.
- **Samples** (:mod:`.marching`): coarse steps of half an occupancy cell, fine steps of
  ``step_ratio`` voxels inside occupied cells only; ``contract`` adds a far part evenly spaced
  in inverse distance. A first pass without gradients finds what light reaches each sample;
  only samples it reaches get gradients (early ray termination) and only samples whose weight
  shows get a colour. The light left at the end of a ray takes the colour of the ray's end
  point (``background=last-sample``: far content and sky live on the outer shell).
- **Occupancy**: an EMA grid updated every ``occupancy_every`` steps from the first step,
  every cell during the warm-up (nerfacc), which skips nothing yet.
- **Coarse-to-fine**: the lattice grows from ``resolution_init`` to ``resolution_final`` at
  the ``growth_at`` fractions of the run. An explicit grid has no spectral bias of its own:
  its resolution is what makes it fit low frequencies first (the paper's Fig. 2 prior).
- **Distortion loss** (mip-NeRF 360, ``distortion`` > 0): pulls each ray's weights together,
  against floaters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from rainyscape.components import Callback, ParamGroup, TrainState
from rainyscape.config.schema import bounded
from rainyscape.errors import ConfigError
from rainyscape.fields.grid import (COLOR_GROUP, DENSITY_GROUP, NETWORK_GROUP, ColorNet, GridGrowth,
                                    check_growth)
from rainyscape.fields.feature_grids import axis_sizes
from rainyscape.fields.grid_encodings import Encoding, HashEncoding, PlanesEncoding, VMEncoding
from rainyscape.fields.marching import PackedSamples, march
from rainyscape.fields.occupancy import EmaOccupancy
from rainyscape.fields.packed import distortion, packed_weights, ray_starts, ray_sum
from rainyscape.fields.ray_field import RayField
from rainyscape.fields.space import GridSpace, SampleRays
from rainyscape.scene import SceneData



class PackedGridField(RayField):
    """Packed-sample field: a feature grid, a tiny colour MLP, EMA occupancy, coarse-to-fine growth."""

    description = "packed-sample feature-grid field: TensoRF VM / K-Planes / hash features, EMA occupancy, coarse-to-fine"

    @dataclass
    class Config:
        encoding: Literal["vm", "planes", "hash"] = "vm"
        layout: Literal["auto", "box", "contract", "ndc"] = "auto"  # auto: ndc if forward-facing, else contract
        # defaults: the best PSNR per CPU second of the measured settings (docs/benchmarks.md)
        inner: float = bounded(0.5, hi=0.99, above=0.0)  # contract: the grid's share given to the scene box
        box_scale: float = bounded(1.0, above=0.0)  # the scene box scaled about its centre
        resolution_init: int = bounded(16, 2, 1024)  # cube root of the lattice size at the start ...
        resolution_final: int = bounded(128, 2, 1024)  # ... and after the last growth
        growth_at: tuple[float, ...] = bounded((0.05, 0.1, 0.2, 0.3, 0.4), 0.0, 1.0)  # fractions of the run where it grows
        density_components: int = bounded(4, 1)  # vm: components per mode of the density grid
        color_components: int = bounded(8, 1)  # vm: components per mode of the appearance grid
        planes_scales: int = bounded(4, 1)  # planes: scales, each twice as fine as the last
        planes_density_channels: int = bounded(8, 1)
        planes_color_channels: int = bounded(16, 1)
        hash_levels: int = bounded(16, 1)
        hash_features: int = bounded(2, 1)
        hash_log2_table: int = bounded(17, 4)
        hash_base: int = bounded(16, 2)  # coarsest level's lattice
        hash_hidden: int = bounded(64, 1)
        feature_dim: int = bounded(16, 1)  # appearance features fed to the colour MLP
        hidden: int = bounded(32, 1)  # colour MLP width
        view_freqs: int = bounded(2, 0)  # positional-encoding frequencies of the view direction
        step_ratio: float = bounded(0.5, above=0.0)  # fine sample spacing in voxels
        far_fine: int = bounded(1, 1)  # contract: samples per coarse step beyond the box (2 per shell cell)
        density_scale: float = bounded(25.0, above=0.0)  # sigma = scale * softplus(raw + shift)
        density_shift: float = bounded(-5.0, -30.0, 30.0)  # a zero grid: a light haze the first steps carve
        background: Literal["last-sample", "black", "white"] = "last-sample"
        occupancy_resolution: int = bounded(64, 2)  # cube root of the occupancy cells
        occupancy_every: int = bounded(8, 1)  # steps between updates
        occupancy_warmup: float = bounded(0.1, 0.0, 1.0)  # fraction of the run: every cell updated, none skipped
        occupancy_threshold: float = bounded(0.01, 0.0, 1.0)  # opacity of one fine step below which a cell is empty
        occupancy_dilate: int = bounded(1, 0)  # occupied cells also mark their neighbours within this many cells
        occupancy_decay: float = bounded(0.8, 0.0, 1.0)  # nerfacc 0.95 every 16 steps: too slow for 1500-step runs
        weight_threshold: float = bounded(1e-4, 0.0, 1.0)  # colour only where a sample's weight reaches this
        transmittance_threshold: float = bounded(1e-4, 0.0, 1.0)  # samples behind this much opacity get no gradient
        distortion: float = bounded(0.0, 0.0)  # weight of mip-NeRF 360's distortion loss (0: off)
        lr_density: float = bounded(0.1, 0.0)
        lr_color: float = bounded(0.1, 0.0)
        lr_network: float = bounded(1e-3, 0.0)
        lr_decay: float = bounded(0.1, above=0.0)  # every lr x lr_decay per lr_decay_steps (exponentially)
        lr_decay_steps: int = bounded(3000, 0)
        chunk: int = bounded(8192, 1)  # rays per chunk when rendering without gradients
        train_chunk: int = bounded(0, 0)  # rays per gradient-checkpointed chunk in training (0: one pass)

    def __init__(self, config: Config, scene: SceneData):
        super().__init__()
        c = self.config = config
        check_growth(c)
        if not 0 < c.inner < 1:
            raise ConfigError(f"field.inner must be in (0, 1), got {c.inner}")
        if not 0 < scene.near < scene.far:
            raise ConfigError(f"scene {scene.name}: need 0 < near < far, got {scene.near}, {scene.far}")
        self.eval_chunk, self.train_chunk = c.chunk, c.train_chunk
        layout = c.layout if c.layout != "auto" else ("ndc" if scene.forward_facing else "contract")
        self.space = GridSpace(scene, layout, c.inner, c.box_scale)
        aspect = self.space.extent().cpu()
        self.register_buffer("grid_resolution", torch.tensor(c.resolution_init))
        self.encoding = self._encoding(c, aspect)
        self.color_net = ColorNet(self.encoding.feature_dim, c.view_freqs, c.hidden)
        self.occupancy = EmaOccupancy(axis_sizes(c.occupancy_resolution, aspect))
        # samples per ray of the last render: marched, given gradients (or all, without), shaded
        self.samples_per_ray = (0.0, 0.0, 0.0)

    @staticmethod
    def _encoding(c: Config, aspect: Tensor) -> Encoding:
        if c.encoding == "vm":
            return VMEncoding(c.resolution_init, aspect, c.density_components, c.color_components, c.feature_dim)
        if c.encoding == "planes":
            return PlanesEncoding(c.resolution_init, c.resolution_final, aspect, c.planes_scales,
                                  c.planes_density_channels, c.planes_color_channels, c.feature_dim)
        return HashEncoding(c.resolution_init, c.resolution_final, aspect, c.hash_levels, c.hash_features,
                            c.hash_log2_table, c.hash_base, c.hash_hidden, c.feature_dim)

    # ------------------------------------------------------------------ geometry

    @property
    def resolution(self) -> int:
        return int(self.grid_resolution)

    @property
    def layout(self) -> str:
        return self.space.layout

    @property
    def final_resolution(self) -> int:
        return self.config.resolution_final

    def stats(self) -> dict[str, float]:
        """The lattice resolution (cube root), the occupied share of the occupancy grid and the
        samples per ray of the last render (evaluated, kept for gradients, shaded)."""
        marched, kept, shaded = self.samples_per_ray
        return {"grid_resolution": self.resolution, "occupied_fraction": round(self.occupancy.fraction(), 4),
                "samples_per_ray": round(marched, 1), "grad_samples_per_ray": round(kept, 1),
                "shaded_per_ray": round(shaded, 1)}

    def _voxel(self, cells_per_axis: tuple[int, int, int]) -> float:
        """Mean edge (sampling-space units) of a cell when the grid cube has these per axis."""
        n = torch.tensor(cells_per_axis, dtype=torch.float32)
        return float((2.0 * self.space.box_half.cpu() / (n * self.space.inner)).mean())

    def steps(self) -> tuple[float, int, int]:
        """(coarse step, fine samples per coarse step, far coarse steps) in sampling-space units."""
        c = self.config
        lattice = tuple(max(1, n - 1) for n in axis_sizes(self.resolution, self.space.extent().cpu()))
        fine = c.step_ratio * self._voxel(lattice)
        # half an occupancy cell, or one fine step where the lattice is coarser than the cells
        coarse = max(0.5 * self._voxel(self.occupancy.sizes), fine)
        per = max(1, round(coarse / fine))
        if self.layout != "contract":
            return coarse, per, 0
        # beyond the box, as inside it, coarse steps of half an occupancy cell: two per
        # cell across the shell (a count fixed by the occupancy grid, not by the lattice)
        shell_cells = float(torch.tensor(self.occupancy.sizes, dtype=torch.float32).mean()) * (1.0 - self.space.inner) / 2.0
        return coarse, per, max(1, math.ceil(2.0 * shell_cells))

    def _sigma(self, raw: Tensor) -> Tensor:
        return self.config.density_scale * F.softplus(raw + self.config.density_shift)

    def density(self, points: Tensor) -> Tensor:
        """Volume density (P,) at world points (P, 3) of the normalised scene (for export)."""
        return self.space.density_at(points, lambda g: self._sigma(self.encoding.density(g)))

    # ----------------------------------------------------------------- rendering

    def _march(self, rays: SampleRays) -> PackedSamples:
        coarse, per, far = self.steps()
        step = coarse / rays.length  # the NDC parameter moves |d| NDC units per unit
        return march(rays.origins, rays.directions, rays.t_a, rays.t_b,
                     rays.t_far if self.layout == "contract" else None, step, per, far,
                     lambda q: self.occupancy.lookup(self.space.to_grid(q)), jitter=self.training,
                     far_fine=self.config.far_fine)

    def _points(self, rays: SampleRays, s: PackedSamples) -> tuple[Tensor, Tensor]:
        """Grid coordinates (S, 3) and interval lengths (S,) of packed samples."""
        g = self.space.to_grid(rays.origins[s.ray] + s.t[:, None] * rays.directions[s.ray])
        return g, (s.t1 - s.t0) * rays.length[s.ray]

    # coarse-step bounds of the segments the first pass marches in turn (the far part is last)
    SEGMENTS = (8.0, 24.0, 56.0, 120.0)

    @torch.no_grad()
    def _first_pass(self, rays: SampleRays, s: PackedSamples, n: int):
        """Density of the samples that light reaches, segment by segment along the rays: a
        segment is evaluated only for rays that the segments before it left transparent
        enough (early ray termination without a sequential march). Returns the evaluated
        samples, their grid points, interval lengths and densities."""
        c = self.config
        limit = -math.log(max(c.transmittance_threshold, 1e-12))
        segment = torch.bucketize(s.u0, torch.tensor(self.SEGMENTS, device=s.u0.device))
        segment = torch.where(s.far, torch.full_like(segment, len(self.SEGMENTS) + 1), segment)
        optical = torch.zeros(n, device=s.t.device)
        done = torch.zeros(len(s), dtype=torch.bool, device=s.t.device)
        g_all = torch.zeros(len(s), 3, device=s.t.device)
        d_all, sigma_all = torch.zeros(len(s), device=s.t.device), torch.zeros(len(s), device=s.t.device)
        for k in range(len(self.SEGMENTS) + 2):
            idx = ((segment == k) & (optical[s.ray] < limit)).nonzero()[:, 0]
            if len(idx) == 0:
                continue
            part = s.select(idx)
            g, deltas = self._points(rays, part)
            sigma = self._sigma(self.encoding.density(g))
            optical = optical.index_add(0, part.ray, sigma * deltas)
            done[idx], g_all[idx], d_all[idx], sigma_all[idx] = True, g, deltas, sigma
        return s.select(done), g_all[done], d_all[done], sigma_all[done]

    def render_rays(self, origins: Tensor, directions: Tensor, z_scale: Tensor) -> dict[str, Tensor]:
        c = self.config
        n = origins.shape[0]
        rays = self.space.sample_rays(origins, directions)
        s = self._march(rays)
        enc = self.encoding
        with torch.no_grad():  # what light reaches each sample
            s, g, deltas, sigma = self._first_pass(rays, s, n)
            weights, transmittance, left = packed_weights(sigma, deltas, s.ray, n)
        feats_all = None
        if torch.is_grad_enabled():
            keep = transmittance > c.transmittance_threshold  # a prefix of every ray
            s, g, deltas = s.select(keep), g[keep], deltas[keep]
            if isinstance(enc, HashEncoding):  # one pass gives density and features
                out = enc._out(g)
                raw, feats_all = out[:, 0], out[:, 1:]
            else:
                raw = enc.density(g)
            sigma = self._sigma(raw)
            starts = ray_starts(s.ray, n)
            weights, _, left = packed_weights(sigma, deltas, s.ray, n, starts)
        shade = (weights.detach() >= c.weight_threshold).nonzero()[:, 0]
        self.samples_per_ray = (transmittance.numel() / max(1, n), len(s) / max(1, n), len(shade) / max(1, n))
        # colour where a sample shows and, for the light left at a ray's end, at that end:
        # one appearance lookup for both
        ray_of, w_of, pts = s.ray[shade], weights[shade], g[shade]
        if c.background == "last-sample":
            end = rays.t_far if self.layout == "contract" else torch.maximum(rays.t_b, rays.t_a)
            show = (left.detach() >= c.weight_threshold).nonzero()[:, 0]
            g_end = self.space.to_grid(rays.origins[show] + end[show, None] * rays.directions[show])
            ray_of, w_of = torch.cat([ray_of, show]), torch.cat([w_of, left[show]])
        if feats_all is not None:
            feats = feats_all[shade]
            if c.background == "last-sample":
                feats = torch.cat([feats, enc.appearance(g_end.clamp(-1, 1))])
        else:
            if c.background == "last-sample":
                pts = torch.cat([pts, g_end.clamp(-1, 1)])
            feats = enc.appearance(pts)
        colors = self.color_net(feats, directions[ray_of])
        rgb = torch.zeros_like(origins).index_add(0, ray_of, w_of[:, None] * colors)
        acc = ray_sum(weights, s.ray, n)
        depth = ray_sum(weights * self._distance(rays, s.t, s.ray), s.ray, n)
        if c.background == "last-sample":
            acc = acc + left
            depth = depth + left * self._distance(rays, end, None)
        elif c.background == "white":
            rgb = rgb + left[:, None]
        out = {"rgb": rgb, "depth": depth * z_scale, "acc": acc}
        if self.training and c.distortion > 0 and len(s):
            out["distortion"] = self._distortion(s, weights, left, n)
        return out

    def _distortion(self, s: PackedSamples, weights: Tensor, left: Tensor, n: int) -> Tensor:
        """Distortion loss per ray (R,) over the samples and, as one more interval, the ray's
        end (the light left there): without it, moving all light to the end would be free."""
        _, _, far = self.steps()
        span = max(float(s.u1.max()), 1.0) + (0 if far else 1.0)
        ends = torch.full_like(left, span)
        ray = torch.cat([s.ray, torch.arange(n, device=left.device)])
        order = torch.argsort(ray, stable=True)  # each ray's end after its samples
        u0 = torch.cat([s.u0, ends - 1.0])[order] / span
        u1 = torch.cat([s.u1, ends])[order] / span
        w = torch.cat([weights, left])[order]
        return distortion(w, u0, u1, ray[order], n)

    def _distance(self, rays: SampleRays, t: Tensor, ray: Tensor | None) -> Tensor:
        if self.layout != "ndc":
            return t
        from rainyscape.fields.ndc import ndc_to_distance

        shift, dz = (rays.ndc_shift, rays.ndc_dz) if ray is None else (rays.ndc_shift[ray], rays.ndc_dz[ray])
        return shift + ndc_to_distance(t.clamp(max=1.0 - 1e-4), self.space.near, dz)

    # -------------------------------------------------------------- optimisation

    def param_groups(self) -> list[ParamGroup]:
        c = self.config
        density, color, network = self.encoding.groups()
        network = network + list(self.color_net.parameters())

        def group(name: str, params: list, lr: float) -> ParamGroup:
            # A tiny eps (as instant-ngp): grid gradients are tiny where rays barely reach,
            # and Adam's default 1e-8 would freeze those voxels instead of normalising them.
            return ParamGroup(name, params, lr=lr, lr_decay=c.lr_decay,
                              lr_decay_steps=c.lr_decay_steps, eps=1e-15)

        groups = [group(DENSITY_GROUP, density, c.lr_density)]
        if color:
            groups.append(group(COLOR_GROUP, color, c.lr_color))
        return groups + [group(NETWORK_GROUP, network, c.lr_network)]

    def callbacks(self) -> list[Callback]:
        return [GridGrowth(self), OccupancyUpdate(self)]

    @torch.no_grad()
    def grow(self, resolution: int, optimizers: dict[str, torch.optim.Optimizer] | None = None) -> None:
        """Grow the lattice to ``resolution``; Adam's moments follow resampled parameters."""
        self.encoding.set_resolution(resolution, optimizers or {}, (DENSITY_GROUP, COLOR_GROUP))
        self.grid_resolution.fill_(resolution)

    @torch.no_grad()
    def update_occupancy(self, warmup: bool, generator: torch.Generator | None = None) -> None:
        """One EMA update: the opacity of one fine step *of the final lattice* at random points
        of the cells (the same step whatever the current resolution, so that the values stay
        comparable while the lattice grows)."""
        c = self.config
        lattice = tuple(max(1, n - 1) for n in axis_sizes(c.resolution_final, self.space.extent().cpu()))
        step_grid = c.step_ratio * self._voxel(lattice) / (float(self.space.box_half.mean()) / self.space.inner)

        def opacity(g: Tensor) -> Tensor:
            sigma = self._sigma(self.encoding.density(g))
            return 1.0 - torch.exp(-sigma * step_grid * self.space.length_per_grid(g))

        self.occupancy.update(opacity, warmup, c.occupancy_threshold, c.occupancy_decay, generator,
                              dilate=c.occupancy_dilate)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        # A checkpoint may hold grown grids: grow to its resolution before copying.
        saved = state_dict.get("grid_resolution")
        if saved is not None and int(saved) != self.resolution:
            self.grow(int(saved))
        return super().load_state_dict(state_dict, strict=strict, assign=assign)


class OccupancyUpdate(Callback):
    """Updates the occupancy EMA every ``occupancy_every`` steps, all cells during the warm-up."""

    def __init__(self, field: PackedGridField):
        self.field = field

    def before_step(self, state: TrainState) -> None:
        c = self.field.config
        if state.step % c.occupancy_every == 0:
            self.field.update_occupancy(warmup=state.step < c.occupancy_warmup * state.max_iters)
