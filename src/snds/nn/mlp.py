"""Unconstrained networks: the nominal velocity field of a policy."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

__all__ = ["ACTIVATIONS", "MLP", "FourierFeatures"]

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "leaky_relu": nn.LeakyReLU,
    "relu": nn.ReLU,
    "tanh": nn.Tanh,
    "silu": nn.SiLU,
    "softplus": nn.Softplus,
    "gelu": nn.GELU,
}


class FourierFeatures(nn.Module):
    r"""Random Fourier features :math:`[x, \sin(2\pi B x), \cos(2\pi B x)]`.

    A plain MLP on a low-dimensional input fits high-frequency detail slowly (spectral bias);
    fixed random sinusoids of the input let it fit a handwriting stroke in hundreds, not
    thousands, of steps (Tancik et al., 2020). The raw input is kept so that the network
    still has a linear path far from the data.

    Arguments:
        dim: Input dimension n.
        features: Number m of random frequencies.
        scale: Standard deviation of the frequencies, in cycles per unit of input.
        seed: Seed of the frequencies (they are a buffer, saved with the model).
    """

    def __init__(self, dim: int, *, features: int, scale: float, seed: int = 0) -> None:
        super().__init__()
        generator = torch.Generator().manual_seed(seed)
        frequencies = torch.randn(dim, features, generator=generator) * scale
        self.register_buffer("frequencies", frequencies)
        self.out_features = dim + 2 * features

    def forward(self, x: Tensor) -> Tensor:
        """Encodes states (*, n) as features (*, n + 2m)."""
        angles = (2 * math.pi) * x @ self.frequencies.to(x.dtype)
        return torch.cat([x, torch.sin(angles), torch.cos(angles)], dim=-1)


class MLP(nn.Sequential):
    """A multi-layer perceptron, optionally on random Fourier features of its input.

    Arguments:
        in_features: Input dimension.
        out_features: Output dimension.
        hidden: Widths of the hidden layers.
        activation: A key of :data:`ACTIVATIONS`.
        fourier_features: Number of random frequencies (0: use the raw input).
        fourier_scale: Standard deviation of those frequencies.
        seed: Seed of the random frequencies.
    """

    def __init__(
        self,
        in_features: int,
        out_features: int,
        *,
        hidden: tuple[int, ...] = (256, 256, 128, 128),
        activation: str = "leaky_relu",
        fourier_features: int = 0,
        fourier_scale: float = 1.0,
        seed: int = 0,
    ) -> None:
        if activation not in ACTIVATIONS:
            raise ValueError(f"unknown activation {activation!r}; choose from {list(ACTIVATIONS)}")
        layers: list[nn.Module] = []
        width = in_features
        if fourier_features > 0:
            encoding = FourierFeatures(
                in_features, features=fourier_features, scale=fourier_scale, seed=seed
            )
            layers.append(encoding)
            width = encoding.out_features
        for size in hidden:
            layers += [nn.Linear(width, size), ACTIVATIONS[activation]()]
            width = size
        layers.append(nn.Linear(width, out_features))
        super().__init__(*layers)
