"""The fast CPU field: explicit grids + tiny MLP, grown coarse-to-fine.

Where the grids live is the field's ``GridSpace`` (fields/space.py): for most captures space
is contracted (the content's box is the inner half of the grid cube, everything out to
infinity the shell around it); for forward-facing ones (LLFF, camera arrays) the grid cube is
NeRF's NDC box of the training frustums, so its texels follow the image's pixels at every
depth. A density grid (TensoRF vector-matrix factorised by default, or dense) and a
TensoRF-style factorised colour grid for a tiny MLP cover that cube, with per-axis
resolutions in proportion to its extent so voxels are about cubic.

Samples are evenly spaced (in voxels) along the linear part of a ray (to where it leaves the
content's box; all of it in NDC), then, when contracted, evenly in inverse distance out to
``far``. An occupancy grid skips empty space; a first pass without gradients keeps the samples
light reaches (compiled on a CPU: grid_march.py), and colour is computed only where a
sample's weight matters. Light that is left at the last sample ends there (as in NeRF): far content and sky
live on the shell (the NDC box's far face).

The grids start coarse and grow on a schedule: an explicit grid has no spectral bias of its
own, so its resolution is what makes it fit low frequencies first (the paper's prior).
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
from rainyscape.fields import grid_march
from rainyscape.fields.encoding import encoded_dim, positional_encoding
from rainyscape.fields.feature_grids import DenseGrid, VMTables, axis_sizes
from rainyscape.fields.grid_march import LiveSamples
from rainyscape.fields.occupancy import OccupancyGrid, cell_centers, occupied_cells
from rainyscape.fields.optim_state import replace_adam_param
from rainyscape.fields.packed import distortion, front_weight, packed_weights, ray_starts, ray_sum
from rainyscape.fields.ray_field import RayField
from rainyscape.fields.rendering import (FAR_DELTA, compositing_weights, densities_until_opaque,
                                         near_gradient_scale, sample_deltas, scale_gradient)
from rainyscape.fields.space import GridSpace, SampleRays
from rainyscape.scene import SceneData, points_box

DENSITY_GROUP, COLOR_GROUP, NETWORK_GROUP = "field_density", "field_color", "field_network"


def growth_resolution(step: int, max_iters: int, initial: int, final: int,
                      growth_at: tuple[float, ...]) -> int:
    """Grid resolution at ``step``: ``initial``, then after each fraction in ``growth_at`` of
    the run one more of len(growth_at) steps evenly spaced in log resolution up to ``final``."""
    if not growth_at:
        return final
    done = sum(step >= round(f * max_iters) for f in growth_at)
    level = done / len(growth_at)
    return int(round(math.exp(math.log(initial) * (1 - level) + math.log(final) * level)))


def pixel_matched_resolution(extent: Tensor, width: int, height: int) -> int:
    """The lattice (cube root of its size) with about one texel per image pixel over an NDC
    cube of half sizes ``extent`` (3,): the image spans NDC [-1, 1] on both image axes, so
    an axis of half size h needs h x pixels texels, and axis_sizes shares the lattice in
    proportion to the half sizes."""
    return int(round(max(width, height) * float(extent.prod()) ** (1.0 / 3.0)))


class ColorNet(nn.Module):
    """Colour features + view direction -> rgb: one small hidden layer."""

    def __init__(self, feature_dim: int, view_freqs: int, hidden: int):
        super().__init__()
        self.view_freqs = view_freqs
        self.mlp = nn.Sequential(nn.Linear(feature_dim + encoded_dim(3, view_freqs), hidden),
                                 nn.ReLU(), nn.Linear(hidden, 3))

    def forward(self, features: Tensor, viewdirs: Tensor) -> Tensor:
        x = torch.cat([features, positional_encoding(viewdirs, self.view_freqs)], -1)
        return torch.sigmoid(self.mlp(x))


CONTRACT_INNER = 0.5  # the grid cube's share given to the box in the contracted layout


class GridField(RayField):
    """Fast field: explicit density + factorised colour grids, tiny MLP, coarse-to-fine growth."""

    description = "fast grid field (CPU/GPU): explicit grids + tiny MLP, occupancy grid, coarse-to-fine"
    provides = ("distortion", "front_weight")

    @dataclass
    class Config:
        # up to 1024 (the GPU recipe's final lattice); a dense 1024^3 grid is already 4 GiB
        resolution_init: int = bounded(16, 2, 1024)  # cube root of the lattice size of the contracted cube at the start ...
        # 512: colour texels about a pixel wide on the cpu set's 128 px views (the old 128 lost
        # 3.8 dB on their training views; docs/benchmarks.md, issue 27)
        resolution_final: int = bounded(512, 2, 1024)  # ... and after the last growth (NDC: at most a texel per pixel)
        # fractions of the run where it grows: most of the run on the coarse lattices, whose
        # steps are cheap (samples are spaced in voxels); the old (0.05 ... 0.4) over half the
        # steps ended 2.2 dB lower on real fern in the same CPU time (docs/benchmarks.md, issue 27)
        growth_at: tuple[float, ...] = bounded((0.1, 0.2, 0.4, 0.6, 0.8), 0.0, 1.0)
        # vm: measured 1.1 dB better after 300 steps and twice as fast per step as dense (docs/benchmarks.md)
        density_grid: Literal["dense", "vm"] = "vm"
        density_components: int = bounded(4, 1)  # vm density: components per mode
        color_components: int = bounded(24, 1)  # factorised colour grid: components per mode (x3 modes)
        feature_dim: int = bounded(32, 1)  # colour features fed to the MLP
        hidden: int = bounded(32, 1)  # MLP width
        view_freqs: int = bounded(2, 0)  # positional-encoding frequencies of the view direction
        # 2 voxels of the final 512 lattice: half a voxel of a 128 one, as many samples as before
        step_ratio: float = bounded(2.0, above=0.0)  # sample spacing in voxels
        density_scale: float = bounded(25.0, above=0.0)  # sigma = scale * softplus(grid + shift)
        density_shift: float = -5.0  # a zero grid: a light haze the first steps carve
        box_scale: float = bounded(1.0, above=0.0)  # the uncontracted region: the box scaled about its centre
        # points: the box of the scene's sparse points, triangulated from the training views
        # when it has none; scene: the scene's box (its parser's points', else the cameras'
        # reach); auto: points when there are enough, else scene. The cameras' reach made the
        # cpu set's texels 2 to 3.4x wider than the points' box and its training views 2.2 dB
        # lower (docs/benchmarks.md, "The grid's box from the sparse points")
        box: Literal["auto", "scene", "points"] = "auto"
        # auto: ndc for forward-facing captures (their cameras look within 35 degrees of one
        # direction), else contract; box: the content's box only, nothing outside it
        layout: Literal["auto", "contract", "ndc", "box"] = "auto"
        # last-sample: the last sample takes the light that is left (NeRF), so far content and
        # sky live on the outer shell; a learned constant would rather explain the commonest
        # surface colour (a grey road) and drain its density.
        background: Literal["last-sample", "black", "white"] = "last-sample"
        # contract: a ray ends where its contracted coordinate reaches this share of the cube
        # (0.98: 25 box half-sizes out, beyond which everything to infinity is the last 5
        # texels of a 512 lattice); the cameras' reach as a far bound (0: the scene's far) cut
        # off distant content and cost 2.0 dB held out on the cpu set (docs/benchmarks.md,
        # "Where a contracted ray ends")
        shell_reach: float = bounded(0.98, 0.0, 0.999)
        occupancy_resolution: int = bounded(64, 2)
        occupancy_from: float = bounded(0.2, 0.0, 1.0)  # fraction of the run before the first occupancy update
        occupancy_every: int = bounded(25, 1)  # steps between updates
        occupancy_threshold: float = bounded(0.01, 0.0, 1.0)  # opacity of one step below which a cell is empty
        weight_threshold: float = bounded(1e-4, 0.0, 1.0)  # colour is computed only where a sample's weight reaches this
        transmittance_threshold: float = bounded(1e-4, 0.0, 1.0)  # samples behind this much opacity get no gradient
        distortion: float = bounded(0.0, 0.0)  # weight of mip-NeRF 360's distortion loss (0: off)
        # gradients of samples nearer a camera than this share of the cameras' mean distance to
        # the scene centre scaled by (d / that)^2 against near-camera floaters (0: off)
        near_gradient: float = bounded(0.0, 0.0)
        lr_density: float = bounded(0.1, 0.0)
        lr_color: float = bounded(0.1, 0.0)
        lr_network: float = bounded(1e-3, 0.0)
        # every lr x lr_decay per lr_decay_steps (exponentially); 0.1 slowed the grids while
        # they still had most of the views to fit (1.2-1.4 dB lost on the cpu set's yard and plaza)
        lr_decay: float = bounded(0.5, above=0.0)
        lr_decay_steps: int = bounded(3000, 0)
        # the last 5 % of the run anneal every rate a further 10x: the 512 lattice arrives at
        # 80 %, so an earlier anneal starves it (crossroad: 0.8 lost 0.3 dB); +0.08 dB on the
        # cpu set, +0.12 on fern (docs/benchmarks.md, "A late anneal of the grid field's rates")
        anneal_at: float = bounded(0.95, 0.0, 1.0)  # fraction of the run where the anneal starts
        anneal_to: float = bounded(0.1, above=0.0)  # its factor at the run's end (1: none)
        chunk: int = bounded(8192, 1)  # rays per chunk when rendering without gradients
        train_chunk: int = bounded(0, 0)  # rays per gradient-checkpointed chunk in training (0: one pass)

    def __init__(self, config: Config, scene: SceneData):
        super().__init__()
        c = self.config = config
        check_growth(c)
        if c.step_ratio <= 0 or c.box_scale <= 0:
            raise ConfigError("field.step_ratio and field.box_scale must be > 0")
        if c.shell_reach and not CONTRACT_INNER < c.shell_reach < 1.0:
            raise ConfigError(f"field.shell_reach: a share of the grid cube beyond the box's "
                              f"{CONTRACT_INNER} (or 0: the scene's far), got {c.shell_reach}")
        if not 0 < scene.near < scene.far:
            raise ConfigError(f"scene {scene.name}: need 0 < near < far, got {scene.near}, {scene.far}")
        self.eval_chunk, self.train_chunk = c.chunk, c.train_chunk
        box = None
        has_points = scene.points is not None and len(scene.points) > 0
        if c.box == "points" and not has_points:
            raise ConfigError(f"field.box=points: scene {scene.name} has no sparse points "
                              f"({scene.points_source}); use field.box=scene")
        if c.box != "scene" and has_points:
            box = points_box(scene.points)
        layout = c.layout if c.layout != "auto" else ("ndc" if scene.forward_facing else "contract")
        self.space = GridSpace(scene, layout, inner=CONTRACT_INNER, box_scale=c.box_scale, box=box,
                               shell_reach=c.shell_reach or None)
        self.final_resolution = c.resolution_final
        if layout == "ndc":
            # NDC texels keep their pixel footprint at every depth: finer than the pixels,
            # they only add parameters that the views pin down more slowly (fern: 256^3 beat
            # 384^3 and 512^3 at the CPU budget, docs/benchmarks.md)
            pixels = pixel_matched_resolution(self.space.extent().cpu(), scene.width, scene.height)
            self.final_resolution = max(c.resolution_init, min(c.resolution_final, pixels))
        self.register_buffer("grid_resolution", torch.tensor(c.resolution_init))
        sizes = axis_sizes(c.resolution_init, self.space.extent().cpu())
        self.density_grid = (DenseGrid(1, sizes) if c.density_grid == "dense"
                             else VMTables(c.density_components, sizes))
        self.color_grid = VMTables(c.color_components, sizes)
        self.basis = nn.Linear(self.color_grid.channels, c.feature_dim, bias=False)
        self.color_net = ColorNet(c.feature_dim, c.view_freqs, c.hidden)
        self.occupancy = OccupancyGrid(c.occupancy_resolution)
        self._sample_counts: tuple[Tensor, int, int] | None = None  # of the last training render
        self.near_reference = c.near_gradient * float(scene.cameras.centers.norm(dim=-1).mean())

    # ------------------------------------------------------------------ geometry

    @property
    def resolution(self) -> int:
        return int(self.grid_resolution)

    def stats(self) -> dict[str, float]:
        """The grids' resolution (cube root of the lattice size), the occupied share of the
        occupancy grid and, from the last training render, the samples a ray marched (those
        past the occupancy grid whose density was evaluated before the ray turned opaque) and
        shaded: light spread along the rays shows as many shaded samples, and they are what a
        step costs."""
        out = {"grid_resolution": self.resolution, "occupied_fraction": round(self.occupancy.fraction(), 4)}
        if self._sample_counts is not None:
            marched, shaded, rays = self._sample_counts
            out["marched_per_ray"] = round(float(marched) / rays, 2)
            out["shaded_per_ray"] = round(shaded / rays, 2)
        return out

    @property
    def layout(self) -> str:
        return self.space.layout

    def step_size(self) -> float:
        """Sample spacing in sampling-space units (world, or NDC) on the linear part of a ray."""
        sizes = torch.tensor(axis_sizes(self.resolution, self.space.extent().cpu()), dtype=torch.float32)
        voxel = 2.0 * self.space.box_half.cpu() / (self.space.inner * (sizes - 1))
        return self.config.step_ratio * float(voxel.mean())

    def _sigma(self, grid_points: Tensor) -> Tensor:
        """Density at points of the grid cube [-1, 1]^3."""
        raw = self.density_grid.features(grid_points).sum(-1)
        return self.config.density_scale * F.softplus(raw + self.config.density_shift)

    def density(self, points: Tensor) -> Tensor:
        """Volume density (P,) at world points (P, 3) of the normalised scene (for export);
        zero outside the grid cube (NDC and box layouts)."""
        return self.space.density_at(points, self._sigma)

    def _sample_plan(self, rays: SampleRays) -> tuple[Tensor, int, Tensor, int]:
        """How rays are sampled: the t step of the linear part (R,), its slots (the longest
        ray's), each ray's jitter (R, 1) (random in training, 0.5 else) and the far part's
        slots (0: one last sample at t_b instead)."""
        step = self.step_size() / rays.length  # t moves |d| sampling-space units per unit
        n_lin = max(1, math.ceil(float(((rays.t_b - rays.t_a) / step).max())))
        shape = (rays.t_a.shape[0], 1)
        device = rays.t_a.device
        jitter = (torch.rand(shape, device=device) if self.training
                  else torch.full(shape, 0.5, device=device))
        n_far = (max(1, math.ceil((self.resolution - 1) / 4.0 / self.config.step_ratio))
                 if self.layout == "contract" else 0)
        return step, n_lin, jitter, n_far

    def _samples(self, rays: SampleRays) -> tuple[Tensor, Tensor]:
        """Sample parameters t (R, N) and which are real (R, N): evenly spaced on the linear
        part [t_a, t_b]; then, contracted, evenly in inverse distance out to t_far; else one
        last sample at t_b that takes the light that is left."""
        step, n_lin, jitter, n_far = self._sample_plan(rays)
        device = rays.t_a.device
        t_lin = rays.t_a[:, None] + (torch.arange(n_lin, device=device) + jitter) * step[:, None]
        valid = t_lin < rays.t_b[:, None]
        if n_far:
            # Past the box, samples go evenly in inverse distance: evenly in the shell.
            u = (torch.arange(n_far, device=device) + jitter) / n_far
            t_end = 1.0 / ((1.0 - u) / rays.t_b[:, None] + u / rays.t_far[:, None])
        else:
            t_end = rays.t_b[:, None]
        # Padding sits at the first sample after the linear part: zero-length intervals, so a
        # ray renders the same whatever the longest ray of its batch (chunking does not change
        # images).
        t_lin = torch.where(valid, t_lin, t_end[:, :1])
        return torch.cat([t_lin, t_end], -1), torch.cat([valid, torch.ones_like(t_end, dtype=torch.bool)], -1)

    def _last_delta(self) -> float:
        return FAR_DELTA if self.config.background == "last-sample" else 0.0

    @torch.no_grad()
    def _march_dense(self, rays: SampleRays) -> LiveSamples:
        """The live samples, from (rays x slots) tensors (any device; the reference for the
        compiled marcher)."""
        t, valid = self._samples(rays)
        deltas = (sample_deltas(t, last=self._last_delta()) * rays.length[:, None]).clamp_min(0.0)
        g = self.space.to_grid(rays.origins[:, None] + t[..., None] * rays.directions[:, None])
        live = valid & self.occupancy.lookup(2.0 * g)  # the occupancy grid spans [-2, 2]^3
        if self.config.background == "last-sample":
            live[:, -1] = True  # it must stay able to take the light that is left
        threshold = self.config.transmittance_threshold
        sigma, evaluated = densities_until_opaque(live, deltas, lambda r, s: self._sigma(g[r, s]), threshold)
        _, transmittance = compositing_weights(sigma, deltas)
        idx = (live & (transmittance > threshold)).nonzero(as_tuple=True)
        rank = torch.cumsum(valid, -1) - 1
        return LiveSamples(idx[0], t[idx], deltas[idx], g[idx], sigma[idx], rank[idx],
                           t.shape[1], evaluated.sum())

    def _compiled(self, origins: Tensor) -> bool:
        """Whether the compiled first pass can run: a vector-matrix density, on the CPU."""
        grid = self.density_grid
        return isinstance(grid, VMTables) and grid_march.usable(grid.plane, origins)

    def _march(self, rays: SampleRays) -> LiveSamples:
        """The samples light reaches (occupied, in front of where the ray turns opaque): the
        compiled marcher where it can run, else the dense one."""
        if not self._compiled(rays.origins):
            return self._march_dense(rays)
        step, n_lin, jitter, n_far = self._sample_plan(rays)
        c, grid = self.config, self.density_grid
        return grid_march.march(grid.plane, grid.line, grid.layout(), self.occupancy.occupied,
                                rays.origins, rays.directions, rays.t_a, rays.t_b, rays.t_far,
                                step, jitter[:, 0], rays.length, n_lin, n_far, self.space.inner,
                                self._last_delta(), c.background == "last-sample",
                                c.density_scale, c.density_shift, c.transmittance_threshold)

    # ----------------------------------------------------------------- rendering

    def render_rays(self, origins: Tensor, directions: Tensor, z_scale: Tensor) -> dict[str, Tensor]:
        rays = self.space.sample_rays(origins, directions)
        live = self._march(rays)
        n = len(origins)
        starts = ray_starts(live.ray, n)
        distance = self.space.distance(rays, live.t, live.ray)
        sigma, near = live.sigma, None  # near: per-sample gradient scale (field.near_gradient)
        if torch.is_grad_enabled():
            # Only the samples light still reaches get gradients (early ray termination).
            grid = self.density_grid
            sigma = (grid_march.pass_density(grid.plane, grid.line, grid.layout(), live,
                                             self.config.density_scale)
                     if self._compiled(origins) else self._sigma(live.g))
            if self.near_reference > 0:
                near = near_gradient_scale(distance, self.near_reference)
                sigma = scale_gradient(sigma, near)
        weights, _, _ = packed_weights(sigma, live.delta, live.ray, n, starts)
        # Colour only where it shows; composited sparsely, straight into the rays.
        shade = (weights.detach() >= self.config.weight_threshold).nonzero()[:, 0]
        if self.training:  # read by stats() at log time only: no device sync here
            self._sample_counts = (live.evaluated, len(shade), n)
        ray = live.ray[shade]
        feats = self.basis(self.color_grid.features(live.g[shade]))
        rgb_samples = self.color_net(feats, directions[ray])
        if near is not None:
            rgb_samples = scale_gradient(rgb_samples, near[shade][:, None])
        rgb = torch.zeros_like(origins).index_add(0, ray, weights[shade][:, None] * rgb_samples)
        acc = ray_sum(weights, live.ray, n)
        rest = (1.0 - acc).clamp_min(0.0)
        if self.config.background == "white":
            rgb = rgb + rest[:, None]
        depth = (ray_sum(weights * distance, live.ray, n) + rest * self.space.end_distance(rays)) * z_scale
        out = {"rgb": rgb, "depth": depth, "acc": acc}
        if self.training and (self.config.distortion > 0 or "distortion" in self.requested):
            # the samples are evenly spaced in the sampling space (voxels, then the contracted
            # shell), so a sample's rank among the ray's real ones is that space's coordinate
            s0 = live.rank.to(weights.dtype) / live.slots
            out["distortion"] = distortion(weights, s0, s0 + 1.0 / live.slots, live.ray, n, starts)
        if self.training and "front_weight" in self.requested:
            out["front_weight"] = front_weight(weights, distance, live.ray, n, starts)
        return out

    # -------------------------------------------------------------- optimisation

    def param_groups(self) -> list[ParamGroup]:
        c = self.config
        color = self.color_grid.factors()
        network = list(self.basis.parameters()) + list(self.color_net.parameters())

        def group(name: str, params: list, lr: float) -> ParamGroup:
            # A tiny eps (as instant-ngp): grid gradients are tiny where rays barely reach,
            # and Adam's default 1e-8 would freeze those voxels instead of normalising them.
            return ParamGroup(name, params, lr=lr, lr_decay=c.lr_decay,
                              lr_decay_steps=c.lr_decay_steps, eps=1e-15,
                              anneal_at=c.anneal_at, anneal_to=c.anneal_to)

        return [group(DENSITY_GROUP, self.density_grid.factors(), c.lr_density),
                group(COLOR_GROUP, color, c.lr_color),
                group(NETWORK_GROUP, network, c.lr_network)]

    def callbacks(self) -> list[Callback]:
        return [GridGrowth(self), OccupancyUpdate(self)]

    @torch.no_grad()
    def grow(self, resolution: int, optimizers: dict[str, torch.optim.Optimizer] | None = None) -> None:
        """Resample the grids to ``resolution``; Adam's moments are resampled alike."""
        sizes = axis_sizes(resolution, self.space.extent().cpu())
        optimizers = optimizers or {}
        for name, grid in ((DENSITY_GROUP, self.density_grid), (COLOR_GROUP, self.color_grid)):
            for old, new, remap in grid.resize(sizes):
                if name in optimizers:
                    replace_adam_param(optimizers[name], old, new, remap)
        self.grid_resolution.fill_(resolution)

    @torch.no_grad()
    def update_occupancy(self) -> None:
        """Mark cells whose density would make one marching step at least threshold-opaque."""
        g = cell_centers(self.occupancy.resolution, device=self.space.box_half.device) / 2.0
        sigma = self._sigma(g.reshape(-1, 3)).reshape(g.shape[:-1])
        # one step's sampling-space length in grid units, stretched where the grid is contracted
        step_grid = self.step_size() * self.space.inner / float(self.space.box_half.mean())
        alpha = 1.0 - torch.exp(-sigma * step_grid * self.space.length_per_grid(g))
        self.occupancy.set(occupied_cells(alpha, self.config.occupancy_threshold))

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        # A checkpoint may hold grown grids: grow to its resolution before copying.
        saved = state_dict.get("grid_resolution")
        if saved is not None and int(saved) != self.resolution:
            self.grow(int(saved))
        return super().load_state_dict(state_dict, strict=strict, assign=assign)


def check_growth(config) -> None:
    """A grid field's lattice schedule is one it can follow (``grid`` and ``packed-grid``)."""
    if not 2 <= config.resolution_init <= config.resolution_final:
        raise ConfigError(f"field: need 2 <= resolution_init <= resolution_final, got "
                          f"{config.resolution_init}, {config.resolution_final}")
    if any(not 0 <= f <= 1 for f in config.growth_at):
        raise ConfigError(f"field.growth_at: fractions of the run in [0, 1], got {config.growth_at}")


class GridGrowth(Callback):
    """Grows a grid field's lattice on the schedule (``config.resolution_init`` -> the field's
    ``final_resolution`` at ``growth_at``; ``grid`` and ``packed-grid``); the resolution
    follows from the step, so resuming works."""

    def __init__(self, field: nn.Module):
        self.field = field

    def before_step(self, state: TrainState) -> None:
        c = self.field.config
        target = growth_resolution(state.step, state.max_iters, c.resolution_init,
                                   self.field.final_resolution, tuple(c.growth_at))
        if target != self.field.resolution:
            self.field.grow(target, state.optimizers)


class OccupancyUpdate(Callback):
    """Refreshes the occupancy grid every ``occupancy_every`` steps once the field has formed."""

    def __init__(self, field: GridField):
        self.field = field

    def before_step(self, state: TrainState) -> None:
        c = self.field.config
        start = round(c.occupancy_from * state.max_iters)
        if state.step >= start and (state.step - start) % max(1, c.occupancy_every) == 0:
            self.field.update_occupancy()
