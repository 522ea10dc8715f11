"""Positional (Fourier-feature) encoding, as in NeRF."""

from __future__ import annotations

import torch
from torch import Tensor


def encoded_dim(in_dim: int, num_freqs: int, include_input: bool = True) -> int:
    return in_dim * (2 * num_freqs + int(include_input))


def positional_encoding(x: Tensor, num_freqs: int, include_input: bool = True) -> Tensor:
    """[x, sin(2^k x), cos(2^k x) for k < num_freqs] along the last axis.

    Frequencies 1, 2, 4, ... (no factor pi), and per frequency all sines then all cosines,
    the layout of the original NeRF code.
    """
    parts = [x] if include_input else []
    if num_freqs > 0:
        freqs = 2.0 ** torch.arange(num_freqs, dtype=x.dtype, device=x.device)
        scaled = x[..., None, :] * freqs[:, None]  # (..., F, D)
        enc = torch.stack([torch.sin(scaled), torch.cos(scaled)], -2)  # (..., F, 2, D)
        parts.append(enc.flatten(-3))
    return torch.cat(parts, -1)
