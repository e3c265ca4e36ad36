"""Small test-only building blocks shared by several test files."""

import torch
from torch import nn


class IdentityEncoder(nn.Module):
    """w = obs with a fixed observation variance: turns an (ac-)RKN into a textbook linear
    Kalman filter, so its beliefs can be compared with the dense filter of Chapter 1."""

    def __init__(self, var: torch.Tensor) -> None:
        super().__init__()
        self.var = var

    def forward(self, obs):
        return obs, self.var.expand_as(obs)
