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


def seq_data(n=3, T=24, do=3, da=2, seed=1, p_valid=1.0, dtype=torch.float64):
    """Random-walk observations, random actions and a random validity mask, seeded."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(n, T, do, generator=g, dtype=dtype).cumsum(1) * 0.3
    act = torch.randn(n, T, da, generator=g, dtype=dtype)
    valid = torch.rand(n, T, generator=g) < p_valid
    return obs, act, valid


def small_hip(m=3, do=3, da=2, task_dim=4, encoder="ba", seed=0):
    """A small float64 HiP-RSSM (nonlinear task term) built from the public constructors."""
    from pgm_wm.acrkn import MLPControl
    from pgm_wm.aggregation import BayesianContextEncoder
    from pgm_wm.hiprssm import HiPRSSM, NonlinearTaskTransform, RecurrentContextEncoder
    from pgm_wm.rkn import ObservationEncoder

    torch.manual_seed(seed)
    acrkn = AcRKN(ObservationEncoder(do, m, (16,)), LocallyLinearTransition(m, 3, 1), MLPControl(da, m, (16,)),
                  BeliefDecoder(m, do, (16,), (16,)), diff_shift=torch.full((do,), 0.1),
                  diff_scale=torch.full((do,), 0.5))
    F = 2 * do + da
    enc = BayesianContextEncoder(F, task_dim, (16,)) if encoder == "ba" else RecurrentContextEncoder(F, task_dim, (16,))
    return HiPRSSM(acrkn, enc, NonlinearTaskTransform(task_dim, m, (16,))).to(torch.float64)


def small_mts3(H=4, do=3, da=2, m=4, seed=1):
    """A small float64 2-level MTS3 from the chapter builder."""
    from pgm_wm.mts3 import build_mts3

    with torch.random.fork_rng():
        torch.manual_seed(seed)
        return build_mts3(do, da, m, H, hidden=(8,)).to(torch.float64)
