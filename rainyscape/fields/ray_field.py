"""What ray-marching fields share: window -> rays -> chunks -> RenderOutput."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from rainyscape.cameras import Cameras, Window, window_rays
from rainyscape.components import Field, RenderOutput


class RayField(Field):
    """A field that renders rays independently. Subclasses implement :meth:`render_rays`.

    ``render_rays(origins, directions, z_scale)`` takes (R, 3), (R, 3) unit directions and
    (R,) cosines to the optical axis and returns per-ray tensors: "rgb" (R, 3), "depth"
    (R,) z-depth, "acc" (R,), and any extras shaped (R,) or (R, C) (e.g. "rgb_coarse").
    """

    eval_chunk: int = 4096  # rays per chunk under no_grad (bounds memory at any resolution)
    train_chunk: int = 0  # rays per gradient-checkpointed chunk in training (0: one pass)

    def render_rays(self, origins: Tensor, directions: Tensor, z_scale: Tensor) -> dict[str, Tensor]:
        raise NotImplementedError  # abstract

    def extra_losses(self, output: RenderOutput, target: Tensor) -> dict[str, Tensor]:
        """mip-NeRF 360's distortion loss, weighted by ``config.distortion``, when the field's
        render_rays returned it per ray (training only)."""
        d = output.extras.get("distortion")
        weight = getattr(self.config, "distortion", 0.0)
        if d is None or weight <= 0:
            return {}
        return {"distortion": weight * d.mean()}

    def render(self, cameras: Cameras, window: Window) -> RenderOutput:
        rays = window_rays(cameras, window)
        b, h, w = rays.origins.shape[:3]
        flat = (rays.origins.reshape(-1, 3), rays.directions.reshape(-1, 3), rays.z_scale.reshape(-1))
        out = self._render_chunked(*flat)
        images = {k: v.reshape(b, h, w, -1).permute(0, 3, 1, 2) for k, v in out.items()}
        rgb, depth, acc = images.pop("rgb"), images.pop("depth"), images.pop("acc")
        return RenderOutput(rgb=rgb, depth=depth, acc=acc, extras=images)

    def _render_chunked(self, origins: Tensor, directions: Tensor, z_scale: Tensor) -> dict[str, Tensor]:
        grad = torch.is_grad_enabled()
        chunk = self.train_chunk if grad else self.eval_chunk
        n = origins.shape[0]
        if chunk <= 0 or n <= chunk:
            return self.render_rays(origins, directions, z_scale)
        parts: list[dict[str, Tensor]] = []
        for start in range(0, n, chunk):
            args = (origins[start:start + chunk], directions[start:start + chunk],
                    z_scale[start:start + chunk])
            if grad:
                # Recompute activations in backward: memory of one chunk, not of the batch.
                parts.append(checkpoint(self.render_rays, *args, use_reentrant=False))
            else:
                parts.append(self.render_rays(*args))
        return {k: torch.cat([p[k] for p in parts], 0) for k in parts[0]}
