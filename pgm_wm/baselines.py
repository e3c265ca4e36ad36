r"""Baseline world models with the same interface and output convention as the ac-RKN.

Every model here has ``forward(obs (B, T, do), actions (B, T, da), mask (B, T)) -> (mean, var)``
with index ``t`` predicting :math:`o_{t+1}` from the observed :math:`o_{\le t}` and
:math:`a_{\le t}`, and the same difference/memory readout as :class:`pgm_wm.acrkn.AcRKN`
(:class:`pgm_wm.acrkn.DifferenceReadout`, Eq. acrkn-diff). All output a diagonal Gaussian
(variance via ``elu + 1``) so that they can be trained and scored with the same NLL.

Actions enter these models *as inputs* (concatenated to the observation), the usual practice
for RNNs — the alternative the ac-RKN is compared against. A model of this kind has no way to
"skip" a missing observation, so at a masked step it is fed its own last prediction instead
(the memory :math:`m_t` of Eq. acrkn-diff) together with a 0/1 flag telling it whether the
input is a real observation; this is what makes open-loop multi-step prediction possible.

* :class:`RKNActionsAsObs` — the Chapter 3 RKN whose encoder sees :math:`[m_t, a_t, \text{flag}]`;
  the Kalman update always runs (the "fake observation" graphical model).
* :class:`LSTMBaseline`, :class:`GRUBaseline` — encoder MLP, recurrent cell, Gaussian head.
* :class:`FFNNBaseline` — a feed-forward net on a window of the last ``window`` inputs (a
  Markov-``window`` model); missing observations are replaced by its own predictions.

Chapter 6 appends a Transformer baseline at the end of this file.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor, nn

from ._checks import mask_observations
from .acrkn import DifferenceReadout, check_sequences
from .factorized import FactorizedBelief, factorized_update
from .layers import GaussianHead, mlp
from .rkn import BeliefDecoder, LocallyLinearTransition, ObservationEncoder

__all__ = [
    "FeedbackModel",
    "RKNActionsAsObs",
    "LSTMBaseline",
    "GRUBaseline",
    "FFNNBaseline",
]


class FeedbackModel(nn.Module):
    """Base class: a step-by-step world model fed :math:`[m_t, a_t, \\text{flag}_t]` at every step.

    Subclasses implement :meth:`init_state` and :meth:`step` (returning the normalized
    difference's mean and variance); :meth:`forward` runs the loop with the memory rule.
    """

    def __init__(self, obs_dim: int, action_dim: int, predict_differences: bool = True,
                 diff_shift: Tensor | Sequence[float] | None = None,
                 diff_scale: Tensor | Sequence[float] | None = None) -> None:
        super().__init__()
        if obs_dim <= 0 or action_dim <= 0:
            raise ValueError(f"obs_dim: need obs_dim > 0 and action_dim > 0, got {obs_dim}, {action_dim}")
        self.obs_dim, self.action_dim = obs_dim, action_dim
        self.input_dim = obs_dim + action_dim + 1
        self.readout = DifferenceReadout(obs_dim, predict_differences, diff_shift, diff_scale)

    def init_state(self, batch: int, like: Tensor) -> object:  # pragma: no cover - abstract
        raise NotImplementedError

    def step(self, state: object, x: Tensor) -> tuple[object, Tensor, Tensor]:  # pragma: no cover
        raise NotImplementedError

    def forward(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``(mean, var)`` each ``(B, T, do)``; index ``t`` predicts ``obs[:, t + 1]``."""
        mask = check_sequences(obs, actions, mask, self.obs_dim, self.action_dim)
        B, T = obs.shape[:2]
        if mask is None:
            mask = torch.ones(B, T, dtype=torch.bool, device=obs.device)
        obs = mask_observations(obs, mask)
        state = self.init_state(B, obs)
        last: Tensor | None = None
        means, vars_ = [], []
        for t in range(T):
            mem = DifferenceReadout.memory(obs[:, t], mask[:, t], last)
            x = torch.cat([mem, actions[:, t], mask[:, t, None].to(obs.dtype)], dim=-1)
            state, d_mean, d_var = self.step(state, x)
            mu, var = self.readout.step(mem, d_mean, d_var)
            means.append(mu)
            vars_.append(var)
            last = mu
        return torch.stack(means, 1), torch.stack(vars_, 1)


class RKNActionsAsObs(FeedbackModel):
    """The Chapter 3 RKN with actions treated as (part of) the observation.

    Encoder input :math:`[m_t, a_t, \\text{flag}_t]`; the factorized Kalman update runs at every step
    (the action has to get in somehow); predict without a control term; the decoder reads the
    prior :math:`z^-_{t+1}` as in the ac-RKN. Same sizes as the ac-RKN it is compared with.
    """

    def __init__(self, obs_dim: int, action_dim: int, latent_obs_dim: int, num_basis: int = 15,
                 bandwidth: int = 3, enc_hidden: Sequence[int] = (64,), dec_hidden: Sequence[int] = (64,),
                 init_var: float = 10.0, **readout_kw) -> None:
        super().__init__(obs_dim, action_dim, **readout_kw)
        self.latent_obs_dim, self.init_var = latent_obs_dim, init_var
        self.encoder = ObservationEncoder(self.input_dim, latent_obs_dim, enc_hidden)
        self.transition = LocallyLinearTransition(latent_obs_dim, num_basis, bandwidth)
        self.decoder = BeliefDecoder(latent_obs_dim, obs_dim, dec_hidden, dec_hidden)

    def init_state(self, batch: int, like: Tensor) -> FactorizedBelief:
        return FactorizedBelief.isotropic((batch,), self.latent_obs_dim, self.init_var, like.dtype, like.device)

    def step(self, state: FactorizedBelief, x: Tensor) -> tuple[FactorizedBelief, Tensor, Tensor]:
        w, w_var = self.encoder(x)
        post = factorized_update(state, w, w_var, validate=False)
        prior = self.transition(post)
        d_mean, d_var = self.decoder(prior)
        return prior, d_mean, d_var


class _RNNBaseline(FeedbackModel):
    cell_type: type[nn.Module] = nn.GRUCell

    def __init__(self, obs_dim: int, action_dim: int, hidden: int = 64, enc_hidden: Sequence[int] = (64,),
                 dec_hidden: Sequence[int] = (64,), **readout_kw) -> None:
        super().__init__(obs_dim, action_dim, **readout_kw)
        if hidden <= 0:
            raise ValueError(f"hidden: must be positive, got {hidden}")
        self.hidden = hidden
        self.encoder = mlp(self.input_dim, enc_hidden) if len(enc_hidden) else nn.Identity()
        self.cell = self.cell_type(enc_hidden[-1] if len(enc_hidden) else self.input_dim, hidden)
        self.head = GaussianHead(hidden, obs_dim, dec_hidden)


class LSTMBaseline(_RNNBaseline):
    """LSTM world model: ``MLP encoder -> LSTMCell(hidden) -> Gaussian head``."""

    cell_type = nn.LSTMCell

    def init_state(self, batch: int, like: Tensor) -> tuple[Tensor, Tensor]:
        z = torch.zeros(batch, self.hidden, dtype=like.dtype, device=like.device)
        return z, z.clone()

    def step(self, state: tuple[Tensor, Tensor], x: Tensor) -> tuple[tuple[Tensor, Tensor], Tensor, Tensor]:
        h, c = self.cell(self.encoder(x), state)
        mean, var = self.head(h)
        return (h, c), mean, var


class GRUBaseline(_RNNBaseline):
    """GRU world model: ``MLP encoder -> GRUCell(hidden) -> Gaussian head``."""

    cell_type = nn.GRUCell

    def init_state(self, batch: int, like: Tensor) -> Tensor:
        return torch.zeros(batch, self.hidden, dtype=like.dtype, device=like.device)

    def step(self, state: Tensor, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        h = self.cell(self.encoder(x), state)
        mean, var = self.head(h)
        return h, mean, var


class FFNNBaseline(FeedbackModel):
    """Feed-forward world model on the last ``window`` inputs :math:`[m_s, a_s, \\text{flag}_s]_{s=t-window+1..t}`.

    Before the sequence starts the window is filled with copies of the first input. The trunk
    (``hidden`` widths) uses a bounded activation (``tanh`` by default) and the Gaussian head is
    linear on it, so every decoded difference is bounded: fed its own predictions over a long
    open loop, an untrained FFNN drifts at most linearly instead of exploding (with ReLU it
    reached NaN after about 3600 steps).
    """

    def __init__(self, obs_dim: int, action_dim: int, window: int = 5, hidden: Sequence[int] = (64, 64),
                 activation: type[nn.Module] = nn.Tanh, **readout_kw) -> None:
        super().__init__(obs_dim, action_dim, **readout_kw)
        if window <= 0:
            raise ValueError(f"window: must be positive, got {window}")
        if len(hidden) == 0:
            raise ValueError("hidden: need at least one hidden layer")
        self.window = window
        self.trunk = mlp(window * self.input_dim, hidden, activation=activation)
        self.head = GaussianHead(hidden[-1], obs_dim, ())

    def init_state(self, batch: int, like: Tensor) -> Tensor | None:
        return None

    def step(self, state: Tensor | None, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        if state is None:
            state = x.unsqueeze(1).expand(-1, self.window, -1)
        else:
            state = torch.cat([state[:, 1:], x.unsqueeze(1)], dim=1)
        mean, var = self.head(self.trunk(state.reshape(state.shape[0], -1)))
        return state, mean, var


# ----------------------------------------------------------------------------- Chapter 6: Transformer
__all__ += ["alibi_causal_bias", "TransformerBaseline"]


def alibi_causal_bias(T: int, n_heads: int, like: Tensor) -> Tensor:
    r"""Additive attention bias ``(n_heads, T, T)``: causal (``-inf`` above the diagonal) with a
    linear recency penalty :math:`-s_h\,(i - j)` for query ``i`` and key ``j <= i``, slopes
    :math:`s_h = 2^{-8(h+1)/n_\text{heads}}` (ALiBi, Press et al. 2022). Relative positions only, so a
    model trained on short crops can be run on longer sequences."""
    if T <= 0 or n_heads <= 0:
        raise ValueError(f"T: need T > 0 and n_heads > 0, got {T}, {n_heads}")
    idx = torch.arange(T, device=like.device)
    dist = (idx[:, None] - idx[None, :]).to(like.dtype)  # i - j
    slopes = torch.tensor([2.0 ** (-8.0 * (h + 1) / n_heads) for h in range(n_heads)], dtype=like.dtype,
                          device=like.device)
    bias = -slopes[:, None, None] * dist
    return bias.masked_fill(dist < 0, float("-inf"))


class _AttentionBlock(nn.Module):
    """Pre-norm Transformer block: ``x + MHA(LN(x))``, then ``x + FF(LN(x))``, with an additive
    attention bias ``(heads, T, T)`` (written out with ``scaled_dot_product_attention`` so that
    training and evaluation run the same code; PyTorch's encoder "fast path" in inference mode does
    not treat a per-head float mask the same way)."""

    def __init__(self, d_model: int, n_heads: int, dim_feedforward: int, dropout: float) -> None:
        super().__init__()
        self.n_heads = n_heads
        self.norm1, self.norm2 = nn.LayerNorm(d_model), nn.LayerNorm(d_model)
        self.qkv = nn.Linear(d_model, 3 * d_model)
        self.proj = nn.Linear(d_model, d_model)
        self.ff = mlp(d_model, (dim_feedforward,), d_model)
        self.drop = nn.Dropout(dropout)

    def forward(self, x: Tensor, bias: Tensor) -> Tensor:
        B, T, d = x.shape
        q, k, v = self.qkv(self.norm1(x)).reshape(B, T, 3, self.n_heads, d // self.n_heads).permute(2, 0, 3, 1, 4)
        att = torch.nn.functional.scaled_dot_product_attention(q, k, v, attn_mask=bias)  # (B, heads, T, dh)
        x = x + self.drop(self.proj(att.transpose(1, 2).reshape(B, T, d)))
        return x + self.drop(self.ff(self.norm2(x)))


class TransformerBaseline(nn.Module):
    r"""A small *direct multi-step* Transformer world model (the "Multi-Transformer" competitor of
    the MTS3 chapter), with the world-model interface ``forward(obs, actions, mask) -> (mean, var)``.

    Token :math:`x_t = [m_t o_t,\ m_t,\ a_t]` (:math:`m_t` the 0/1 mask) -> linear embedding ->
    ``n_layers`` pre-norm self-attention blocks with a causal ALiBi bias (:func:`alibi_causal_bias`)
    -> Gaussian head (variance ``elu + 1``). Index ``t`` sees observed :math:`o_{\le t}` and
    :math:`a_{\le t}` and predicts :math:`o_{t+1}`. All predictions of a horizon come out of **one**
    pass: a missing observation is simply absent (its token carries only the action), the model's
    own predictions are never fed back, so errors cannot accumulate through feedback. ``min_var`` is
    a floor added to the predicted variance (as in :class:`pgm_wm.mts3.MTS3`).
    """

    def __init__(self, obs_dim: int, action_dim: int, d_model: int = 32, n_heads: int = 2, n_layers: int = 2,
                 dim_feedforward: int = 64, head_hidden: Sequence[int] = (32,), dropout: float = 0.0,
                 min_var: float = 1e-4) -> None:
        super().__init__()
        if min_var < 0:
            raise ValueError(f"min_var: must be >= 0, got {min_var}")
        self.min_var = float(min_var)
        if obs_dim <= 0 or action_dim <= 0:
            raise ValueError(f"obs_dim: need obs_dim > 0 and action_dim > 0, got {obs_dim}, {action_dim}")
        if d_model <= 0 or n_heads <= 0 or d_model % n_heads:
            raise ValueError(f"d_model: must be a positive multiple of n_heads, got {d_model}, {n_heads}")
        if n_layers <= 0:
            raise ValueError(f"n_layers: must be positive, got {n_layers}")
        self.obs_dim, self.action_dim, self.n_heads = obs_dim, action_dim, n_heads
        self.embed = nn.Linear(obs_dim + 1 + action_dim, d_model)
        self.blocks = nn.ModuleList(_AttentionBlock(d_model, n_heads, dim_feedforward, dropout)
                                    for _ in range(n_layers))
        self.norm = nn.LayerNorm(d_model)
        self.head = GaussianHead(d_model, obs_dim, head_hidden)

    def forward(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``(mean, var)`` each ``(B, T, do)``; index ``t`` predicts ``obs[:, t + 1]``."""
        mask = check_sequences(obs, actions, mask, self.obs_dim, self.action_dim)
        B, T = obs.shape[:2]
        flag = (torch.ones(B, T, 1, dtype=obs.dtype, device=obs.device) if mask is None
                else mask[..., None].to(obs.dtype))
        obs = mask_observations(obs, flag[..., 0] > 0)
        h = self.embed(torch.cat([obs, flag, actions], dim=-1))
        bias = alibi_causal_bias(T, self.n_heads, h)  # (heads, T, T), broadcast over the batch
        for block in self.blocks:
            h = block(h, bias)
        h = self.norm(h)
        mean, var = self.head(h)
        return mean, var + self.min_var
