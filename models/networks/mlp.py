"""A plain multi-layer perceptron (the state world model's network; reusable by reward heads)."""

from __future__ import annotations

import torch
from torch import nn

ACTIVATIONS: dict[str, type[nn.Module]] = {"silu": nn.SiLU, "gelu": nn.GELU, "mish": nn.Mish, "relu": nn.ReLU}


class MLP(nn.Module):
    """``depth`` hidden layers of ``width`` units (Linear, optional LayerNorm, activation), then a linear head.

    ``(..., in_dim) -> (..., out_dim)``.
    """

    def __init__(self, in_dim: int, out_dim: int, width: int, depth: int, activation: str = "silu",
                 layer_norm: bool = False) -> None:
        super().__init__()
        if activation not in ACTIVATIONS:
            raise ValueError(f"activation {activation!r}: use one of {', '.join(ACTIVATIONS)}")
        if min(in_dim, out_dim, width, depth) < 1:
            raise ValueError(f"MLP sizes must be positive (in {in_dim}, out {out_dim}, width {width}, depth {depth})")
        layers: list[nn.Module] = []
        dim = in_dim
        for _ in range(depth):
            layers.append(nn.Linear(dim, width))
            if layer_norm:
                layers.append(nn.LayerNorm(width))
            layers.append(ACTIVATIONS[activation]())
            dim = width
        layers.append(nn.Linear(dim, out_dim))
        self.layers = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.layers(x)
