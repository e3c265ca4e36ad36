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
import torch.nn.functional as F
from torch import Tensor, nn

from ._checks import mask_observations
from .acrkn import DifferenceReadout, check_sequences
from .factorized import FactorizedBelief, factorized_update
from .layers import GaussianHead, elup1, mlp
from .rkn import BeliefDecoder, LocallyLinearTransition, ObservationEncoder

__all__ = [
    "FeedbackModel",
    "RKNActionsAsObs",
    "LSTMBaseline",
    "GRUBaseline",
    "FFNNBaseline",
]


class FeedbackModel(nn.Module):
    """Base class: a step-by-step world model fed :math:`[m_t, a_t, \text{flag}_t]` at every step.

    Subclasses implement :meth:`init_state` and :meth:`step` (returning the normalized
    difference's mean and variance); :meth:`forward_reference` runs the loop with the memory rule,
    step by step. :meth:`forward` runs the same loop with less work inside it: a subclass may
    override :meth:`prepare` (the parts of the input known before the loop, computed for all
    steps at once), :meth:`advance` (one step that returns only what the next step needs) and
    :meth:`variance` (the decoded variance, which is never fed back, for all steps after the
    loop). The defaults reduce to :meth:`step`; :meth:`forward` is tested equal to
    :meth:`forward_reference` for every baseline.
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

    def prepare(self, actions: Tensor, flags: Tensor) -> Tensor:
        """The input parts known before the loop, ``(B, T, ·)``: by default ``[a_t, flag_t]``."""
        return torch.cat([actions, flags], dim=-1)

    def advance(self, state: object, memory: Tensor, prepared: Tensor) -> tuple[object, Tensor, Tensor]:
        """One step from the memory :math:`m_t` and ``prepared[:, t]``: ``(state, feature,
        delta_mean)``; :meth:`variance` turns the stacked features into the decoded variances."""
        state, d_mean, d_var = self.step(state, torch.cat([memory, prepared], dim=-1))
        return state, d_var, d_mean

    def variance(self, features: Tensor) -> Tensor:
        """The decoded variances ``(B, T, do)`` from the stacked features of :meth:`advance`."""
        return features

    def _inputs(self, obs: Tensor, actions: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        mask = check_sequences(obs, actions, mask, self.obs_dim, self.action_dim, model=self)
        B, T = obs.shape[:2]
        if mask is None:
            mask = torch.ones(B, T, dtype=torch.bool, device=obs.device)
        return mask_observations(obs, mask), actions, mask

    def forward(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``(mean, var)`` each ``(B, T, do)``; index ``t`` predicts ``obs[:, t + 1]``."""
        obs, actions, mask = self._inputs(obs, actions, mask)
        prepared = self.prepare(actions, mask[..., None].to(obs.dtype))
        state = self.init_state(obs.shape[0], obs)
        last: Tensor | None = None
        means, features = [], []
        # one unbind instead of an index per step: the backward of ``prepared[:, t]`` would
        # write a zero tensor the size of all of ``prepared`` at every step
        for obs_t, mask_t, prepared_t in zip(obs.unbind(1), mask.unbind(1), prepared.unbind(1)):
            mem = DifferenceReadout.memory(obs_t, mask_t, last)
            state, feature, d_mean = self.advance(state, mem, prepared_t)
            last = self.readout.step_mean(mem, d_mean)
            means.append(last)
            features.append(feature)
        return torch.stack(means, 1), self.readout.step_var(self.variance(torch.stack(features, 1)))

    def forward_reference(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """:meth:`forward` written plainly: :meth:`step` and the readout at every step."""
        obs, actions, mask = self._inputs(obs, actions, mask)
        state = self.init_state(obs.shape[0], obs)
        last: Tensor | None = None
        means, vars_ = [], []
        for t in range(obs.shape[1]):
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

    # the fast loop: the encoder's first layer acts on [m_t, a_t, flag_t]; its action and flag
    # columns are applied to all steps before the loop, only the memory columns inside it; the
    # variance head (never fed back) runs once on all hidden states after the loop
    def _first(self) -> nn.Linear | None:
        first = self.encoder[0] if isinstance(self.encoder, nn.Sequential) and len(self.encoder) else None
        return first if isinstance(first, nn.Linear) else None

    def prepare(self, actions: Tensor, flags: Tensor) -> Tensor:
        first = self._first()
        x = torch.cat([actions, flags], dim=-1)
        return x if first is None else F.linear(x, first.weight[:, self.obs_dim:], first.bias)

    def _features(self, memory: Tensor, prepared: Tensor) -> Tensor:
        first = self._first()
        if first is None:
            return self.encoder(torch.cat([memory, prepared], dim=-1))
        h = F.linear(memory, first.weight[:, :self.obs_dim]) + prepared
        for layer in list(self.encoder)[1:]:
            h = layer(h)
        return h

    def advance(self, state: object, memory: Tensor, prepared: Tensor) -> tuple[object, Tensor, Tensor]:
        state, h = self._cell(state, self._features(memory, prepared))
        return state, h, self.head.mean_net(h)

    def variance(self, features: Tensor) -> Tensor:
        return elup1(self.head.var_net(features))

    def _cell(self, state: object, x: Tensor) -> tuple[object, Tensor]:  # pragma: no cover - abstract
        raise NotImplementedError


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

    def _cell(self, state: tuple[Tensor, Tensor], x: Tensor) -> tuple[tuple[Tensor, Tensor], Tensor]:
        h, c = self.cell(x, state)
        return (h, c), h


class GRUBaseline(_RNNBaseline):
    """GRU world model: ``MLP encoder -> GRUCell(hidden) -> Gaussian head``."""

    cell_type = nn.GRUCell

    def init_state(self, batch: int, like: Tensor) -> Tensor:
        return torch.zeros(batch, self.hidden, dtype=like.dtype, device=like.device)

    def step(self, state: Tensor, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        h = self.cell(self.encoder(x), state)
        mean, var = self.head(h)
        return h, mean, var

    def _cell(self, state: Tensor, x: Tensor) -> tuple[Tensor, Tensor]:
        h = self.cell(x, state)
        return h, h


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

    # the fast loop: the trunk's first layer is a sum over window positions; the action and flag
    # columns of every position are applied to all steps before the loop, so the state is the
    # window of memories only; the variance head runs once on all features after the loop
    def _first_weights(self) -> tuple[Tensor, Tensor]:
        """The first layer's weight split by input part: ``(H, window, do)`` for the memories and
        ``(H, window, da + 1)`` for the actions and flags."""
        first = self.trunk[0]
        weight = first.weight.view(first.out_features, self.window, self.input_dim)
        return weight[..., :self.obs_dim], weight[..., self.obs_dim:]

    def prepare(self, actions: Tensor, flags: Tensor) -> Tensor:
        x = torch.cat([actions, flags], dim=-1)
        padded = torch.cat([x[:, :1].expand(-1, self.window - 1, -1), x], dim=1)  # copies of the first input
        windows = padded.unfold(1, self.window, 1)                                 # (B, T, da + 1, window)
        return torch.einsum("btkw,hwk->bth", windows, self._first_weights()[1]) + self.trunk[0].bias

    def advance(self, state: Tensor | None, memory: Tensor, prepared: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        if state is None:
            state = memory.unsqueeze(1).expand(-1, self.window, -1)
        else:
            state = torch.cat([state[:, 1:], memory.unsqueeze(1)], dim=1)
        w_memory = self._first_weights()[0]
        h = F.linear(state.reshape(state.shape[0], -1), w_memory.reshape(w_memory.shape[0], -1)) + prepared
        for layer in list(self.trunk)[1:]:
            h = layer(h)
        return state, h, self.head.mean_net(h)

    def variance(self, features: Tensor) -> Tensor:
        return elup1(self.head.var_net(features))


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
        """``x: (B, T, d)``, ``bias: (1, heads, T, T)`` (or ``(heads, T, T)``)."""
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
        mask = check_sequences(obs, actions, mask, self.obs_dim, self.action_dim, model=self)
        B, T = obs.shape[:2]
        flag = (torch.ones(B, T, 1, dtype=obs.dtype, device=obs.device) if mask is None
                else mask[..., None].to(obs.dtype))
        obs = mask_observations(obs, flag[..., 0] > 0)
        h = self.embed(torch.cat([obs, flag, actions], dim=-1))
        # (1, heads, T, T), broadcast over the batch; given with four dimensions, the bias lets
        # scaled_dot_product_attention use its fused (flash) CPU kernel: ~2.5x faster than the
        # math path at the chapter's sizes, the same values to float32 rounding
        bias = alibi_causal_bias(T, self.n_heads, h)[None]
        for block in self.blocks:
            h = block(h, bias)
        h = self.norm(h)
        mean, var = self.head(h)
        return mean, var + self.min_var


# ----------------------------------------------------------------------------- trivial references
__all__ += ["last_observed", "RepeatLast", "TrainingMean", "LinearARX"]


def last_observed(obs: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    r"""The last observation at or before every step and its age: ``(memory, steps)``.

    ``memory[:, t] = obs[:, s]`` with :math:`s = \max\{s \le t : \text{mask}_s\}` (zeros where no
    step is observed yet) and ``steps[:, t] = t - s + 1`` (the number of steps from that
    observation to the predicted :math:`o_{t+1}`; ``t + 1`` if there is none). ``obs: (B, T, do)``,
    ``mask: (B, T)`` -> ``(B, T, do)``, ``(B, T)``.
    """
    B, T = obs.shape[:2]
    t = torch.arange(T, device=obs.device).expand(B, T)
    if mask is None:
        return obs, torch.ones(B, T, dtype=obs.dtype, device=obs.device)
    last = torch.where(mask, t, torch.full_like(t, -1)).cummax(dim=1).values
    mem = torch.gather(obs, 1, last.clamp_min(0)[..., None].expand_as(obs))
    mem = mask_observations(mem, last >= 0)
    return mem, torch.where(last >= 0, t - last + 1, t + 1).to(obs.dtype)


def _stat_buffer(x: Tensor | Sequence[float] | None, dim: int, default: float, name: str) -> Tensor:
    v = torch.full((dim,), default) if x is None else torch.as_tensor(x, dtype=torch.get_default_dtype()).clone()
    if v.shape != (dim,):
        raise ValueError(f"{name}: expected shape ({dim},), got {tuple(v.shape)}")
    return v


def _valid_or_all(obs: Tensor, valid: Tensor | None) -> Tensor:
    from ._checks import check_mask, check_tensor

    check_tensor("obs", obs, 3)
    if not bool(torch.isfinite(obs if valid is None else obs[valid.bool()]).all()):
        raise ValueError("obs: contains NaN or infinite values at valid steps")
    if valid is None:
        return torch.ones(obs.shape[:2], dtype=torch.bool, device=obs.device)
    return check_mask("valid", valid, tuple(obs.shape[:2]))


class RepeatLast(nn.Module):
    r"""Repeat-last reference: a random walk, :math:`\hat o_{t+1} = o_s` (the last observation,
    :func:`last_observed`) with variance :math:`(t - s + 1)\,\sigma^2_\Delta` per dimension.

    ``step_var`` :math:`\sigma^2_\Delta: (do,)` is the mean squared one-step difference of the
    training data (:meth:`fit`). Actions are ignored. World-model interface
    ``forward(obs, actions, mask) -> (mean, var)``, index ``t`` predicts :math:`o_{t+1}`.
    """

    def __init__(self, obs_dim: int, step_var: Tensor | Sequence[float] | None = None) -> None:
        super().__init__()
        if obs_dim <= 0:
            raise ValueError(f"obs_dim: must be positive, got {obs_dim}")
        self.obs_dim = obs_dim
        v = _stat_buffer(step_var, obs_dim, 1.0, "step_var")
        if not bool((v > 0).all()):
            raise ValueError("step_var: must be positive")
        self.register_buffer("step_var", v)

    @classmethod
    def fit(cls, obs: Tensor, valid: Tensor | None = None, min_var: float = 1e-8) -> "RepeatLast":
        """``step_var`` = mean of :math:`(o_{t+1} - o_t)^2` over the pairs with both steps valid."""
        v = _valid_or_all(obs, valid)
        pair = (v[:, 1:] & v[:, :-1]).to(obs.dtype)[..., None]
        if float(pair.sum()) == 0:
            raise ValueError("valid: no pair of consecutive valid steps")
        d2 = torch.where(pair > 0, obs[:, 1:] - obs[:, :-1], torch.zeros((), dtype=obs.dtype)) ** 2
        var = (d2 * pair).sum((0, 1)) / pair.sum((0, 1))
        return cls(obs.shape[-1], var.clamp_min(min_var)).to(obs.dtype)

    def forward(self, obs: Tensor, actions: Tensor | None = None, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        mask = check_sequences(obs, actions, mask, self.obs_dim)
        mem, steps = last_observed(obs, mask)
        return mem, steps[..., None] * self.step_var.to(obs.dtype)


class TrainingMean(nn.Module):
    r"""Training-mean reference: :math:`\hat o_{t+1} = \bar o` with variance :math:`s^2`, the mean and
    (biased) variance per dimension of the valid training observations (:meth:`fit`). Ignores every
    input but its shape."""

    def __init__(self, mean: Tensor | Sequence[float], var: Tensor | Sequence[float]) -> None:
        super().__init__()
        m = torch.as_tensor(mean, dtype=torch.get_default_dtype()).clone()
        if m.ndim != 1 or m.numel() == 0:
            raise ValueError(f"mean: expected a vector (do,), got shape {tuple(m.shape)}")
        v = _stat_buffer(var, m.numel(), 1.0, "var")
        if not bool((v > 0).all()):
            raise ValueError("var: must be positive")
        self.obs_dim = m.numel()
        self.register_buffer("mean", m)
        self.register_buffer("var", v)

    @classmethod
    def fit(cls, obs: Tensor, valid: Tensor | None = None, min_var: float = 1e-8) -> "TrainingMean":
        v = _valid_or_all(obs, valid)
        x = obs[v]
        if x.shape[0] == 0:
            raise ValueError("valid: no valid step")
        return cls(x.mean(0), x.var(0, unbiased=False).clamp_min(min_var)).to(obs.dtype)

    def forward(self, obs: Tensor, actions: Tensor | None = None, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        check_sequences(obs, actions, mask, self.obs_dim)
        shape = obs.shape
        return self.mean.to(obs.dtype).expand(shape).clone(), self.var.to(obs.dtype).expand(shape).clone()


class LinearARX(nn.Module):
    r"""Linear ARX reference of order :math:`p`, fit in closed form (:meth:`fit`):

    .. math:: \hat o_{t+1} = c + \sum_{i=0}^{p-1} A_i\, m_{t-i} + \sum_{i=0}^{p-1} B_i\, a_{t-i},

    with the memory :math:`m_t` = the observation if observed, else the model's own previous
    prediction (the feedback rule of Eq. acrkn-diff), so it predicts open-loop through gaps.
    Before the sequence starts, the lags are copies of the first memory / action. Variance: the
    per-dimension mean squared one-step residual of the fit (a one-step variance; it does not
    grow over an open loop). ``weight: (do, p (do + da))`` acts on
    :math:`x_t = [m_t, \dots, m_{t-p+1}, a_t, \dots, a_{t-p+1}]`. An unfitted model (zero
    weights) predicts :math:`c = 0`.
    """

    def __init__(self, obs_dim: int, action_dim: int, order: int = 2) -> None:
        super().__init__()
        if obs_dim <= 0 or action_dim < 0:
            raise ValueError(f"obs_dim: need obs_dim > 0 and action_dim >= 0, got {obs_dim}, {action_dim}")
        if not isinstance(order, int) or order <= 0:
            raise ValueError(f"order: must be a positive int, got {order!r}")
        self.obs_dim, self.action_dim, self.order = obs_dim, action_dim, order
        self.register_buffer("weight", torch.zeros(obs_dim, order * (obs_dim + action_dim)))
        self.register_buffer("bias", torch.zeros(obs_dim))
        self.register_buffer("var", torch.ones(obs_dim))

    @staticmethod
    def _lags(x: Tensor, order: int) -> Tensor:
        """``x: (B, T, d)`` -> ``(B, T, order d)`` with ``[x_t, x_{t-1}, ...]``, padded with ``x_0``."""
        pad = torch.cat([x[:, :1].expand(-1, order - 1, -1), x], 1)
        return torch.cat([pad[:, order - 1 - i: pad.shape[1] - i] for i in range(order)], -1)

    @classmethod
    def fit(cls, obs: Tensor, actions: Tensor, order: int = 2, ridge: float = 1e-6,
            valid: Tensor | None = None) -> "LinearARX":
        r"""Ridge least squares: :math:`\min_{W, c} \sum_t \|o_{t+1} - W x_t - c\|^2 + \lambda\|W\|_F^2`
        over every :math:`t \ge p - 1` whose steps :math:`t-p+1 .. t+1` are all valid (the bias is not
        penalized), solved from the normal equations; ``var`` is the mean squared residual."""
        v = _valid_or_all(obs, valid)
        check_sequences(obs, actions, None)
        if ridge < 0:
            raise ValueError(f"ridge: must be >= 0, got {ridge}")
        model = cls(obs.shape[-1], actions.shape[-1], order).to(obs.dtype)
        T = obs.shape[1]
        if T <= order:
            raise ValueError(f"obs: need more than order={order} steps, got {T}")
        o = mask_observations(obs, v)
        X = torch.cat([cls._lags(o, order), cls._lags(actions, order)], -1)[:, order - 1:T - 1]
        Y = o[:, order:]
        ok = torch.stack([v[:, s:T - order + s] for s in range(order + 1)], 0).all(0)
        X, Y = X[ok], Y[ok]
        if X.shape[0] == 0:
            raise ValueError("valid: no fully valid window of order + 1 steps")
        X1 = torch.cat([X, torch.ones(X.shape[0], 1, dtype=X.dtype)], 1)
        reg = torch.full((X1.shape[1],), float(ridge), dtype=X.dtype)
        reg[-1] = 0.0
        sol = torch.linalg.solve(X1.T @ X1 + torch.diag(reg), X1.T @ Y)  # (k + 1, do)
        with torch.no_grad():
            model.weight.copy_(sol[:-1].T)
            model.bias.copy_(sol[-1])
            model.var.copy_(((Y - X1 @ sol) ** 2).mean(0).clamp_min(1e-8))
        return model

    def forward(self, obs: Tensor, actions: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        mask = check_sequences(obs, actions, mask, self.obs_dim, self.action_dim, model=self)
        W, c = self.weight.to(obs.dtype), self.bias.to(obs.dtype)
        p, do = self.order, self.obs_dim
        var = self.var.to(obs.dtype).expand(obs.shape)
        a_lags = self._lags(actions, p)
        Wo, Wa = W[:, :p * do], W[:, p * do:]
        if mask is None or bool(mask.all()):  # no feedback: one matrix product
            return self._lags(obs, p) @ Wo.T + a_lags @ Wa.T + c, var
        obs = mask_observations(obs, mask)
        hist: list[Tensor] = []
        means, last = [], None
        for t in range(obs.shape[1]):
            mem = DifferenceReadout.memory(obs[:, t], mask[:, t], last)
            hist = [mem] * p if not hist else [mem] + hist[:p - 1]
            last = torch.cat(hist, -1) @ Wo.T + a_lags[:, t] @ Wa.T + c
            means.append(last)
        return torch.stack(means, 1), var
