"""The paper's field: NeRF (Mildenhall et al. 2020) as in nerf-pytorch.

Positional encoding, an 8 x 256 MLP with a skip at layer 4, density and view-dependent
colour heads, 64 stratified coarse + 64 inverse-CDF fine samples per ray (a separate
fine network), density noise while training, NDC for forward-facing scenes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from rainyscape.components import ParamGroup
from rainyscape.config.schema import bounded
from rainyscape.errors import ConfigError
from rainyscape.fields.encoding import encoded_dim, positional_encoding
from rainyscape.fields.ndc import average_pose, ndc_near, ndc_points, ndc_rays, ndc_to_distance
from rainyscape.fields.ray_field import RayField
from rainyscape.fields.rendering import compositing_weights, composite, sample_deltas
from rainyscape.fields.sampling import sample_pdf, stratified_samples
from rainyscape.scene import SceneData


class NerfMLP(nn.Module):
    """(position, direction) -> (raw density, raw rgb), NeRF's architecture."""

    def __init__(self, pos_freqs: int, dir_freqs: int, depth: int, width: int,
                 skips: tuple[int, ...]):
        super().__init__()
        self.pos_freqs, self.dir_freqs, self.skips = pos_freqs, dir_freqs, tuple(skips)
        pos_dim, dir_dim = encoded_dim(3, pos_freqs), encoded_dim(3, dir_freqs)
        layers = [nn.Linear(pos_dim, width)]
        for i in range(depth - 1):  # layer i + 1 reads the input again after a skip at layer i
            layers.append(nn.Linear(width + pos_dim if i in self.skips else width, width))
        self.trunk = nn.ModuleList(layers)
        self.density = nn.Linear(width, 1)
        self.feature = nn.Linear(width, width)
        self.view = nn.Linear(width + dir_dim, width // 2)
        self.color = nn.Linear(width // 2, 3)

    def _trunk(self, points: Tensor) -> Tensor:
        x = positional_encoding(points, self.pos_freqs)
        h = x
        for i, layer in enumerate(self.trunk):
            h = F.relu(layer(h))
            if i in self.skips:
                h = torch.cat([x, h], -1)
        return h

    def forward(self, points: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        h = self._trunk(points)
        sigma = self.density(h)[..., 0]
        d = positional_encoding(directions, self.dir_freqs)
        h = F.relu(self.view(torch.cat([self.feature(h), d], -1)))
        return sigma, self.color(h)

    def raw_density(self, points: Tensor) -> Tensor:
        return self.density(self._trunk(points))[..., 0]


class NerfMLPField(RayField):
    """NeRF (the paper's field): positional encoding, 8x256 MLP, 64 coarse + 64 fine samples."""

    description = "NeRF MLP (paper): 8x256 MLP, 64 coarse + 64 fine samples, NDC for forward-facing"

    @dataclass
    class Config:
        pos_freqs: int = bounded(10, 0)
        dir_freqs: int = bounded(4, 0)
        depth: int = bounded(8, 1)
        width: int = bounded(256, 1)
        skips: tuple[int, ...] = bounded((4,), 0)
        samples_coarse: int = bounded(64, 2)
        samples_fine: int = bounded(64, 0)
        perturb: bool = True  # stratified jitter while training
        density_noise: float = bounded(1.0, 0.0)  # std of the noise added to raw density while training
        lindisp: bool = False  # sample linearly in inverse depth (bounded scenes only)
        ndc: Literal["auto", "on", "off"] = "auto"  # auto: NDC when the scene is forward-facing
        lr: float = bounded(5e-4, 0.0)
        lr_decay: float = bounded(0.1, above=0.0)  # nerf-pytorch: 10x decay every 250k steps
        lr_decay_steps: int = bounded(250_000, 0)
        chunk: int = bounded(4096, 1)  # rays per chunk when rendering without gradients
        train_chunk: int = bounded(1024, 0)  # rays per gradient-checkpointed chunk in training (0: one pass)

    def __init__(self, config: Config, scene: SceneData):
        super().__init__()
        c = self.config = config
        if c.samples_coarse < 2:
            raise ConfigError(f"field.samples_coarse must be at least 2, got {c.samples_coarse}")
        if c.samples_fine < 0:
            raise ConfigError(f"field.samples_fine must be >= 0, got {c.samples_fine}")
        if not 0 < scene.near < scene.far:
            raise ConfigError(f"scene {scene.name}: need 0 < near < far, got {scene.near}, {scene.far}")
        self.eval_chunk, self.train_chunk = c.chunk, c.train_chunk
        net = dict(pos_freqs=c.pos_freqs, dir_freqs=c.dir_freqs, depth=c.depth, width=c.width,
                   skips=tuple(c.skips))
        self.coarse = NerfMLP(**net)
        self.fine = NerfMLP(**net) if c.samples_fine > 0 else None
        self.near, self.far = float(scene.near), float(scene.far)
        self.use_ndc = c.ndc == "on" or (c.ndc == "auto" and scene.forward_facing)
        # NDC is defined in the frame of the average training camera (LLFF's recentring).
        cams = scene.cameras[scene.train_indices or list(range(len(scene.cameras)))]
        frame = average_pose(cams.c2w.float())
        self.register_buffer("ndc_frame", frame, persistent=False)
        self.ndc_scale = (float(2 * cams.fx.mean() / cams.width), float(2 * cams.fy.mean() / cams.height))
        self.ndc_near = ndc_near(frame, scene.points, scene.near)  # NeRF's LLFF rule (fields/ndc.py)

    # ------------------------------------------------------------------ optimisation

    def param_groups(self) -> list[ParamGroup]:
        c = self.config
        return [ParamGroup("field", list(self.parameters()), lr=c.lr, lr_decay=c.lr_decay,
                           lr_decay_steps=c.lr_decay_steps)]

    def extra_losses(self, output, target: Tensor) -> dict[str, Tensor]:
        coarse = output.extras.get("rgb_coarse")
        if coarse is None or self.fine is None:
            return {}
        return {"coarse": F.mse_loss(coarse, target)}

    # --------------------------------------------------------------------- rendering

    def _to_ndc_frame(self, points: Tensor) -> Tensor:
        return (points - self.ndc_frame[:3, 3]) @ self.ndc_frame[:3, :3]

    def density(self, points: Tensor) -> Tensor:
        """Volume density (P,) at world points (P, 3) of the normalised scene (for export)."""
        if self.use_ndc:
            points = ndc_points(self._to_ndc_frame(points), *self.ndc_scale, self.ndc_near)
        net = self.fine if self.fine is not None else self.coarse
        return F.relu(net.raw_density(points))

    def _shade(self, net: NerfMLP, points: Tensor, viewdirs: Tensor, t: Tensor,
               step_scale: Tensor) -> tuple[Tensor, Tensor]:
        """Weights (R, N) and colours (R, N, 3) of samples at parameters ``t`` (R, N)."""
        raw_sigma, raw_rgb = net(points, viewdirs[:, None].expand_as(points))
        if self.training and self.config.density_noise > 0:
            raw_sigma = raw_sigma + torch.randn_like(raw_sigma) * self.config.density_noise
        deltas = sample_deltas(t) * step_scale[:, None]
        weights, _ = compositing_weights(F.relu(raw_sigma), deltas)
        return weights, torch.sigmoid(raw_rgb)

    def render_rays(self, origins: Tensor, directions: Tensor, z_scale: Tensor) -> dict[str, Tensor]:
        c = self.config
        perturb = self.training and c.perturb
        if self.use_ndc:
            o_ref = self._to_ndc_frame(origins)
            d_ref = directions @ self.ndc_frame[:3, :3]
            o, d, t_near = ndc_rays(o_ref, d_ref, *self.ndc_scale, self.ndc_near)
            start = torch.zeros_like(z_scale)
            t = stratified_samples(start, torch.ones_like(start), c.samples_coarse, perturb)
        else:
            # Sample in z-depth between near and far (nerf-pytorch), i.e. distance z / cos.
            o, d = origins, directions / z_scale[:, None]
            near = torch.full_like(z_scale, self.near)
            t = stratified_samples(near, torch.full_like(near, self.far), c.samples_coarse, perturb, c.lindisp)
        step_scale = d.norm(dim=-1)  # sample parameters -> distances
        weights, rgb = self._shade(self.coarse, o[:, None] + t[..., None] * d[:, None], directions, t, step_scale)
        out = {"rgb_coarse": composite(weights, rgb)}
        if self.fine is not None:
            mids = 0.5 * (t[:, 1:] + t[:, :-1])
            t_fine = sample_pdf(mids, weights[:, 1:-1].detach(), c.samples_fine, deterministic=not perturb)
            t, _ = torch.sort(torch.cat([t, t_fine.detach()], -1), -1)
            weights, rgb = self._shade(self.fine, o[:, None] + t[..., None] * d[:, None], directions, t, step_scale)
        out["rgb"] = composite(weights, rgb)
        out["acc"] = weights.sum(-1)
        if self.use_ndc:
            dist = t_near[:, None] + ndc_to_distance(t, self.ndc_near, d_ref[:, 2:3])
            out["depth"] = (weights * dist).sum(-1) * z_scale
        else:
            out["depth"] = (weights * t).sum(-1)  # t is z-depth here
        return out
