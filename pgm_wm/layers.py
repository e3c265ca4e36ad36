"""Small neural-network building blocks shared by every chapter's models."""

from __future__ import annotations

from typing import Sequence

from torch import nn

__all__ = ["mlp"]


def mlp(
    in_dim: int,
    hidden: Sequence[int],
    out_dim: int | None = None,
    activation: type[nn.Module] = nn.ReLU,
) -> nn.Sequential:
    """A multilayer perceptron ``in_dim -> hidden... [-> out_dim]``.

    Each hidden width adds ``Linear -> activation``. With ``out_dim`` a final ``Linear`` layer
    without activation follows (a regression head); with ``out_dim=None`` the network ends with
    the last hidden layer's activation (a feature trunk of size ``hidden[-1]``).
    """
    if out_dim is None and len(hidden) == 0:
        raise ValueError("hidden: a trunk without out_dim needs at least one hidden layer")
    layers: list[nn.Module] = []
    d = in_dim
    for h in hidden:
        layers += [nn.Linear(d, h), activation()]
        d = h
    if out_dim is not None:
        layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)
