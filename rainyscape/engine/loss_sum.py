"""The loss of one training step: the phase's terms, each weighted, each free to stop the
gradient into the render or into one predicted layer."""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from rainyscape.components import Loss, LossContext
from rainyscape.config import LossConfig


def compute_losses(terms: dict[str, tuple[LossConfig, Loss]], ctx: LossContext
                   ) -> tuple[Tensor, dict[str, Tensor]]:
    """Weighted sum of the loss terms, and each term's value (detached, on the device: reading
    it waits for the device, which the caller does only for what it logs) by its key; a term
    with ``detach`` sees the render (``rendered``) or that layer without its gradient, as the
    field is fitted without it (``ctx.field_layers``)."""
    total = torch.zeros((), device=ctx.rendered.device)
    values: dict[str, Tensor] = {}
    for key, (cfg, term) in terms.items():
        c = ctx
        if cfg.detach == "rendered":
            c = replace(ctx, rendered=ctx.rendered.detach())
        elif cfg.detach in ctx.layers:
            layer = ctx.field_layers.get(cfg.detach, ctx.layers[cfg.detach])
            c = replace(ctx, layers={**ctx.layers, cfg.detach: layer.detach()})
        value = term(c)
        total = total + cfg.weight * value
        values[key] = value.detach()
    return total, values


def energy_terms(terms: dict[str, tuple[LossConfig, Loss]], layer: str) -> dict[str, tuple[LossConfig, Loss]]:
    """The terms a layer's latent energy needs: not those that see the layer detached (they
    are constant in it, so they add nothing to its gradient)."""
    return {k: v for k, v in terms.items() if v[0].detach != layer}
