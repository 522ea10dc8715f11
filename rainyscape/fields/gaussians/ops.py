"""Parameter surgery on Gaussians, shared by the densification strategies (as gsplat's
``strategy/ops.py``): every structural change replaces the tensors of the field's
``ParameterDict`` and keeps each parameter's Adam optimiser in step (surviving Gaussians keep
their moments; new or moved ones start from zero)."""

from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor, nn

from rainyscape.fields.gaussians.projection import covariance_factor
from rainyscape.fields.optim_state import replace_adam_param


def replace_params(params: nn.ParameterDict, optimizers: dict[str, torch.optim.Optimizer],
                   new_value: Callable[[str, Tensor], Tensor],
                   new_state: Callable[[Tensor], Tensor], names: list[str] | None = None) -> None:
    """Swap each parameter for ``new_value(name, old)`` and map its Adam moments through
    ``new_state`` (the optimiser keyed by the parameter's name)."""
    for name in names or list(params.keys()):
        old = params[name]
        new = nn.Parameter(new_value(name, old.detach()), requires_grad=old.requires_grad)
        params[name] = new
        if name in optimizers:
            replace_adam_param(optimizers[name], old, new, new_state)


@torch.no_grad()
def remove(params: nn.ParameterDict, optimizers: dict, drop: Tensor) -> None:
    """Delete the Gaussians where ``drop`` (N,) is True."""
    keep = ~drop
    replace_params(params, optimizers, lambda name, p: p[keep], lambda v: v[keep])


@torch.no_grad()
def append(params: nn.ParameterDict, optimizers: dict, keep: Tensor, new: dict[str, Tensor]) -> None:
    """Keep the Gaussians where ``keep`` is True (in order) and append ``new`` (a tensor per
    parameter, one row per new Gaussian), whose Adam moments start at zero."""
    count = len(next(iter(new.values())))

    def state(v: Tensor) -> Tensor:
        return torch.cat([v[keep], v.new_zeros((count, *v.shape[1:]))])

    replace_params(params, optimizers, lambda name, p: torch.cat([p[keep], new[name].to(p)]), state)


@torch.no_grad()
def overwrite(params: nn.ParameterDict, optimizers: dict, index: Tensor, values: dict[str, Tensor]) -> None:
    """Set the Gaussians at ``index`` to ``values`` (a tensor per parameter) and restart
    their Adam moments (their old gradient history belongs to other Gaussians)."""
    def value(name: str, p: Tensor) -> Tensor:
        out = p.clone()
        out[index] = values[name].to(p)
        return out

    def state(v: Tensor) -> Tensor:
        out = v.clone()
        out[index] = 0
        return out

    replace_params(params, optimizers, value, state)


@torch.no_grad()
def cap_opacity(params: nn.ParameterDict, optimizers: dict, value: float) -> None:
    """Clamp every opacity to at most ``value``; its Adam moments restart from zero."""
    cap = math.log(value / (1.0 - value))
    replace_params(params, optimizers, lambda name, p: p.clamp(max=cap), torch.zeros_like,
                   names=["opacities"])


@torch.no_grad()
def split_samples(params: nn.ParameterDict, index: Tensor, copies: int = 2,
                  shrink: float = 1.6) -> dict[str, Tensor]:
    """``copies`` children of each Gaussian at ``index``: positions drawn from it, scales
    divided by ``shrink``, everything else copied (rows grouped per parent)."""
    scales = params["scales"][index].exp()
    factor = covariance_factor(params["quats"][index], scales)  # (S, 3, 3)
    noise = torch.randn(len(index), copies, 3, device=scales.device, dtype=scales.dtype)
    offsets = torch.einsum("sij,skj->ski", factor, noise)
    out = {name: p[index].repeat_interleave(copies, 0) for name, p in params.items()}
    out["means"] = (params["means"][index][:, None] + offsets).reshape(-1, 3)
    out["scales"] = torch.log(scales / shrink).repeat_interleave(copies, 0)
    return out
