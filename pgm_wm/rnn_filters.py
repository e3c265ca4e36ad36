r"""Recurrent-network filters: the LSTM / GRU baselines of Chapter 3, and how to fit a filter.

A :class:`RecurrentFilter` sees exactly what the RKN sees: the encoder's latent observation
:math:`w_t` and its variance :math:`\sigma^{obs}_t` (Eq. rkn-encoder), with missing frames
zeroed and flagged. Instead of a Kalman update and predict it runs a gated recurrent cell over
:math:`x_t = [\,m_t w_t;\ m_t \sigma^{obs}_t;\ m_t\,]` (:math:`m_t\in\{0,1\}` the mask) and decodes
the hidden state :math:`h_t` with a Gaussian head into a mean and a variance. Nothing in the cell
is probabilistic: whatever uncertainty it reports is learned from the loss alone.

:func:`fit_filter` trains any filter ``model(obs, mask) -> (mean, var)`` (the RKN, its
diagonal-only ablation, these baselines) on the per-dimension Gaussian NLL
(:func:`pgm_wm.metrics.gaussian_nll`, Eq. metric-nll) with the generic loop
:func:`pgm_wm.training.fit`, keeping the parameters of the epoch with the best validation NLL;
:func:`evaluate_filter` reports RMSE and NLL on whole sequences.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor, nn

from ._checks import check_mask, check_tensor, mask_observations
from .layers import GaussianHead
from .metrics import gaussian_nll, rmse
from .training import FitHistory, fit, imputation_loss_fn

__all__ = [
    "GaussianHead",  # re-exported from pgm_wm.layers
    "RecurrentFilter",
    "recurrent_hidden_for_budget",
    "count_parameters",
    "FilterData",
    "fit_filter",
    "predict_filter",
    "evaluate_filter",
]

class RecurrentFilter(nn.Module):
    """LSTM or GRU filter over the encoder's ``(w, w_var)`` with the same masking as the RKN.

    Args:
        encoder: maps ``obs: (B, T, obs_dim)`` to ``(w, w_var)`` each ``(B, T, m)`` (e.g. a
            :class:`pgm_wm.rkn.ObservationEncoder`; it must expose ``latent_obs_dim``).
        cell_type: ``"lstm"`` or ``"gru"``.
        hidden: size of the recurrent state.
        decoder: maps ``(B, T, hidden)`` to ``(mean, var)``, e.g. :class:`GaussianHead`.
    """

    def __init__(self, encoder: nn.Module, cell_type: str = "lstm", hidden: int = 32,
                 decoder: nn.Module | None = None, out_dim: int | None = None) -> None:
        super().__init__()
        if cell_type not in ("lstm", "gru"):
            raise ValueError(f"cell_type: expected 'lstm' or 'gru', got {cell_type!r}")
        if hidden <= 0:
            raise ValueError(f"hidden: must be positive, got {hidden}")
        m = getattr(encoder, "latent_obs_dim", None)
        if not isinstance(m, int) or m <= 0:
            raise ValueError("encoder: must expose a positive integer attribute latent_obs_dim")
        if decoder is None:
            if out_dim is None:
                raise ValueError("out_dim: required when no decoder is given")
            decoder = GaussianHead(hidden, out_dim)
        self.encoder, self.decoder = encoder, decoder
        self.cell_type, self.hidden, self.latent_obs_dim = cell_type, hidden, m
        rnn = nn.LSTM if cell_type == "lstm" else nn.GRU
        self.rnn = rnn(input_size=2 * m + 1, hidden_size=hidden, batch_first=True)
        if cell_type == "lstm":
            # the usual "unit forget bias": start by remembering (PyTorch orders gates i, f, g, o)
            with torch.no_grad():
                self.rnn.bias_ih_l0[hidden:2 * hidden].fill_(1.0)
                self.rnn.bias_hh_l0[hidden:2 * hidden].zero_()

    def filter(self, w: Tensor, w_var: Tensor, mask: Tensor | None = None) -> Tensor:
        """Hidden states ``(B, T, hidden)`` from ``w, w_var: (B, T, m)`` and ``mask: (B, T)``."""
        check_tensor("w", w, 3)
        B, T, m = w.shape
        if m != self.latent_obs_dim:
            raise ValueError(f"w: expected latent size {self.latent_obs_dim}, got {m}")
        if tuple(w_var.shape) != (B, T, m):
            raise ValueError(f"w_var: expected shape {(B, T, m)}, got {tuple(w_var.shape)}")
        if mask is None:
            flag = torch.ones(B, T, 1, dtype=w.dtype, device=w.device)
        else:
            flag = check_mask("mask", mask, (B, T)).to(w.dtype)[..., None]
        x = torch.cat([w * flag, w_var * flag, flag], dim=-1)
        h, _ = self.rnn(x)
        return h

    def forward(self, obs: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``obs: (B, T, obs_dim)`` -> ``(mean, var)`` per step; missing frames are zeroed first."""
        check_tensor("obs", obs, 3)
        if mask is not None:
            mask = check_mask("mask", mask, tuple(obs.shape[:2]))
            obs = mask_observations(obs, mask)
        w, w_var = self.encoder(obs)
        return self.decoder(self.filter(w, w_var, mask))


def count_parameters(module: nn.Module) -> int:
    """Number of trainable scalars of ``module``."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def recurrent_hidden_for_budget(cell_type: str, input_dim: int, budget: int) -> int:
    """Largest hidden size whose LSTM/GRU layer has at most ``budget`` parameters.

    A layer with ``g`` gates (4 for LSTM, 3 for GRU) has ``g (h (input_dim + h) + 2 h)``
    parameters (PyTorch keeps two bias vectors). Returns at least 1.
    """
    gates = {"lstm": 4, "gru": 3}.get(cell_type)
    if gates is None:
        raise ValueError(f"cell_type: expected 'lstm' or 'gru', got {cell_type!r}")
    if input_dim <= 0:
        raise ValueError(f"input_dim: must be positive, got {input_dim}")
    h = 1
    while gates * ((h + 1) * (input_dim + h + 1) + 2 * (h + 1)) <= budget:
        h += 1
    return h


@dataclass(frozen=True)
class FilterData:
    """A filtering data set as tensors: ``obs (n, T, d)``, ``mask (n, T)`` bool, ``targets (n, T, k)``."""

    obs: Tensor
    mask: Tensor
    targets: Tensor

    def __post_init__(self) -> None:
        check_tensor("obs", self.obs, 3)
        object.__setattr__(self, "mask", check_mask("mask", self.mask, tuple(self.obs.shape[:2])))
        check_tensor("targets", self.targets, 3)
        if tuple(self.targets.shape[:2]) != tuple(self.obs.shape[:2]):
            raise ValueError(f"targets: expected leading shape {tuple(self.obs.shape[:2])}, "
                             f"got {tuple(self.targets.shape)}")

    @classmethod
    def from_dataset(cls, data: object) -> "FilterData":
        """From a :class:`pgm_wm.datasets.SequenceData` (uses ``obs``, ``valid``, ``targets``)."""
        for attr in ("obs", "valid", "targets"):
            if getattr(data, attr, None) is None:
                raise ValueError(f"data: needs a tensor attribute {attr!r}")
        return cls(data.obs, data.valid, data.targets)

    def __len__(self) -> int:
        return self.obs.shape[0]

    def subset(self, index: Tensor | slice) -> "FilterData":
        return FilterData(self.obs[index], self.mask[index], self.targets[index])


@torch.no_grad()
def predict_filter(model: nn.Module, data: FilterData, batch_size: int = 64) -> tuple[Tensor, Tensor]:
    """``model(obs, mask)`` over ``data`` in batches, in eval mode, without gradients -> ``(mean, var)``."""
    was_training = model.training
    model.eval()
    means, variances = [], []
    for i in range(0, len(data), batch_size):
        mu, var = model(data.obs[i:i + batch_size], data.mask[i:i + batch_size])
        means.append(mu)
        variances.append(var)
    model.train(was_training)
    return torch.cat(means), torch.cat(variances)


def evaluate_filter(model: nn.Module, data: FilterData, batch_size: int = 64) -> dict[str, float]:
    """RMSE (Eq. metric-rmse) and mean Gaussian NLL (Eq. metric-nll) of ``model(obs, mask)``
    on every step, observed or not."""
    mean, var = predict_filter(model, data, batch_size)
    return {"rmse": float(rmse(mean, data.targets)), "nll": float(gaussian_nll(mean, var, data.targets))}


def fit_filter(
    model: nn.Module,
    train: FilterData,
    valid: FilterData,
    epochs: int = 10,
    batch_size: int = 32,
    lr: float = 3e-3,
    clip: float = 5.0,
    seed: int = 0,
    progress: bool = False,
    crop: int | None = None,
    drop_prob: float = 0.0,
    gap_prob: float = 0.0,
    context_steps: int = 5,
    *,
    budget_s: float | None = None,
    patience: int | None = None,
) -> FitHistory:
    """Train ``model(obs, mask) -> (mean, var)`` on the Gaussian NLL of the targets (Eq. metric-nll).

    A thin wrapper of :func:`pgm_wm.training.fit` (Adam, gradient-norm clipping at ``clip``,
    seeded shuffling, random windows of ``crop`` steps if given). After every epoch the NLL on
    the whole validation sequences is recorded, and at the end the parameters of the best
    validation epoch are restored (model selection on the validation split, never on test).

    Frame dropout (training only): with ``drop_prob`` each frame after the first
    ``context_steps`` of a window is additionally hidden, and with ``gap_prob`` a window also
    loses every frame after a random cut (:func:`pgm_wm.training.observation_mask`); ``budget_s`` (CPU seconds)
    and ``patience`` are passed to :func:`pgm_wm.training.fit`. The targets
    stay, so the model must predict through the gaps; the loss covers all steps.
    """
    T = train.obs.shape[1]
    if crop is not None and not 0 < crop <= T:
        raise ValueError(f"crop: must be in [1, {T}], got {crop}")
    if not 0.0 <= drop_prob < 1.0 or not 0.0 <= gap_prob <= 1.0:
        raise ValueError(f"drop_prob: need 0 <= drop_prob < 1 and 0 <= gap_prob <= 1, got {drop_prob}, {gap_prob}")
    loss_fn = imputation_loss_fn(model, 1.0 - drop_prob, context_steps, "nll", gap_prob, filtering=True)
    return fit(loss_fn, model, (train.obs, train.mask, train.targets), batch_size=batch_size,
               epochs=epochs, lr=lr, clip_norm=clip, seed=seed, progress=progress, crop_len=crop,
               valid_fn=lambda: evaluate_filter(model, valid)["nll"], keep_best=True, desc="fit_filter",
               budget_s=budget_s, patience=patience)
