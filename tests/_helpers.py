"""Small test-only building blocks shared by several test files."""

import torch
from torch import nn

from pgm_wm.acrkn import AcRKN, LinearControl
from pgm_wm.rkn import BeliefDecoder, LocallyLinearTransition


class IdentityEncoder(nn.Module):
    """w = obs with a fixed observation variance: turns an (ac-)RKN into a textbook linear
    Kalman filter, so its beliefs can be compared with the dense filter of Chapter 1."""

    def __init__(self, var: torch.Tensor) -> None:
        super().__init__()
        self.var = var

    def forward(self, obs):
        return obs, self.var.expand_as(obs)


def linear_acrkn(m: int, action_dim: int, seed: int, dtype: torch.dtype = torch.float64) -> AcRKN:
    """An ac-RKN that is a linear Kalman filter: one perturbed constant transition with diagonal
    blocks (bandwidth 0), a linear control model, and an identity encoder with fixed
    observation variances ``[0.3, 0.5, 0.7]`` (so ``m`` must be 3)."""
    torch.manual_seed(seed)
    trans = LocallyLinearTransition(m, num_basis=1, bandwidth=0).to(dtype)
    with torch.no_grad():
        for p in (trans.basis_11, trans.basis_12, trans.basis_21, trans.basis_22):
            p.add_(0.1 * torch.randn_like(p))
    r = torch.tensor([0.3, 0.5, 0.7], dtype=dtype)
    ctrl = LinearControl(action_dim, m, init_std=0.5).to(dtype)
    return AcRKN(IdentityEncoder(r), trans, ctrl, BeliefDecoder(m, m).to(dtype), init_var=2.0)
