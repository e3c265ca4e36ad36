r"""Builders for every chapter's models, with the defaults the chapter notebooks use.

Each builder only wires the public constructors together; pass other sizes to explore.

* Chapter 2: :func:`build_set_model` — Bayesian aggregation or a mean/max-pool deep set.
* Chapter 3: :func:`build_image_encoder`, :func:`build_rkn`, :func:`build_recurrent_filter`
  (an LSTM/GRU filter with the RKN's transition parameter budget).
* Chapter 4: :func:`build_acrkn` (MLP, linear or locally linear control; optional
  norm-bounded transition) and :func:`build_baseline` (the recurrent, feed-forward and
  Transformer competitors).
* Chapter 5: :func:`build_hiprssm`.
* Chapter 6: :func:`build_fast_acrkn`, :func:`build_mts3`, :func:`build_hierarchical_mts3`
  (defined in :mod:`pgm_wm.mts3`, re-exported here).

Saving and loading: save the ``state_dict`` and rebuild with the same builder call.
``torch.save(model, path)`` pickles the classes themselves, which ``torch.load``'s default
``weights_only=True`` (torch >= 2.6) refuses to unpickle; a ``state_dict`` holds only tensors,
loads with the default ``torch.load`` and gives bit-identical predictions (tested in
``tests/test_fuzz_saving.py``)::

    torch.save(model.state_dict(), "acrkn.pt")
    model = build_acrkn(obs_dim=2, action_dim=2)          # the same arguments as before
    model.load_state_dict(torch.load("acrkn.pt"))
"""

from __future__ import annotations

from typing import Sequence

from torch import Tensor, nn

from .acrkn import (AcRKN, DifferenceReadout, HybridReadout, LinearControl, LocallyLinearControl, MLPControl,
                    NormBoundedTransition)
from .aggregation import BayesianContextEncoder, MaxPoolContextEncoder, MeanPoolContextEncoder
from .baselines import FFNNBaseline, GRUBaseline, LSTMBaseline, RKNActionsAsObs, TransformerBaseline
from .encoders import ConvTrunk
from .hiprssm import HiPRSSM, LinearTaskTransform, NonlinearTaskTransform, RecurrentContextEncoder
from .layers import GaussianHead
from .mts3 import build_fast_acrkn, build_hierarchical_mts3, build_mts3
from .rkn import RKN, BeliefDecoder, LocallyLinearTransition, ObservationEncoder
from .rnn_filters import RecurrentFilter, count_parameters, recurrent_hidden_for_budget

__all__ = [
    "build_set_model",
    "build_image_encoder",
    "build_rkn",
    "build_recurrent_filter",
    "build_acrkn",
    "build_baseline",
    "build_hiprssm",
    "build_fast_acrkn",
    "build_mts3",
    "build_hierarchical_mts3",
]

Vector = Tensor | Sequence[float] | None


def _choice(name: str, value: str, options: Sequence[str]) -> str:
    if value not in options:
        raise ValueError(f"{name}: expected one of {tuple(options)}, got {value!r}")
    return value


# ----------------------------------------------------------------------------- Chapter 2
def build_set_model(kind: str, in_dim: int, latent_dim: int = 1, hidden: Sequence[int] = (64, 64)) -> nn.Module:
    """A set model ``model(x, mask) -> (mean, var)``: ``kind`` = ``"bayesian"`` (Bayesian
    aggregation, Eq. ba-update), ``"mean"`` or ``"max"`` (deep-set pooling baselines)."""
    cls = {"bayesian": BayesianContextEncoder, "mean": MeanPoolContextEncoder, "max": MaxPoolContextEncoder}
    return cls[_choice("kind", kind, tuple(cls))](in_dim, latent_dim, hidden=hidden)


# ----------------------------------------------------------------------------- Chapter 3
def build_image_encoder(image_shape: Sequence[int], latent_obs_dim: int = 8, channels: Sequence[int] = (8, 16),
                        feature_dim: int = 32) -> ObservationEncoder:
    """The pendulum encoder: :class:`pgm_wm.encoders.ConvTrunk` then the latent-observation heads."""
    if len(image_shape) != 2:
        raise ValueError(f"image_shape: expected (H, W), got {tuple(image_shape)}")
    H, W = image_shape
    return ObservationEncoder(H * W, latent_obs_dim, trunk=ConvTrunk(image_shape, channels=channels,
                                                                      feature_dim=feature_dim),
                              feature_dim=feature_dim)


def build_rkn(image_shape: Sequence[int], out_dim: int = 2, latent_obs_dim: int = 8, num_basis: int = 15,
              bandwidth: int = 3, decoder_hidden: Sequence[int] = (32,), diagonal_only: bool = False) -> RKN:
    """The Chapter 3 RKN on images (``diagonal_only=True``: the diagonal-covariance ablation)."""
    return RKN(build_image_encoder(image_shape, latent_obs_dim),
               LocallyLinearTransition(latent_obs_dim, num_basis, bandwidth),
               BeliefDecoder(latent_obs_dim, out_dim, decoder_hidden, decoder_hidden, log_var_input=True),
               diagonal_only=diagonal_only)


def build_recurrent_filter(cell: str, image_shape: Sequence[int], out_dim: int = 2, latent_obs_dim: int = 8,
                           num_basis: int = 15, bandwidth: int = 3,
                           decoder_hidden: Sequence[int] = (32,)) -> RecurrentFilter:
    """An LSTM / GRU filter (``cell`` = ``"lstm"`` / ``"gru"``) with the same encoder as
    :func:`build_rkn` and a recurrent layer no larger than the RKN's transition model."""
    _choice("cell", cell, ("lstm", "gru"))
    encoder = build_image_encoder(image_shape, latent_obs_dim)  # first: the same initial encoder as build_rkn
    budget = count_parameters(LocallyLinearTransition(latent_obs_dim, num_basis, bandwidth))
    hidden = recurrent_hidden_for_budget(cell, 2 * latent_obs_dim + 1, budget)
    return RecurrentFilter(encoder, cell, hidden, GaussianHead(hidden, out_dim, decoder_hidden, decoder_hidden))


# ----------------------------------------------------------------------------- Chapter 4
def build_acrkn(obs_dim: int = 2, action_dim: int = 2, latent_obs_dim: int = 15, control: str = "mlp",
                bounded: bool = False, hidden: int = 64, num_basis: int = 15, bandwidth: int = 3,
                diff_shift: Vector = None, diff_scale: Vector = None, readout: str = "difference") -> AcRKN:
    """The Chapter 4 ac-RKN: MLP encoder/decoder of width ``hidden``, locally linear transition,
    control model ``"mlp"`` (two hidden layers), ``"linear"`` or ``"locally_linear"``; with
    ``bounded`` the transition is wrapped in :class:`pgm_wm.acrkn.NormBoundedTransition`.
    ``readout``: ``"difference"`` (Eq. (acrkn-diff)), ``"absolute"`` (the decoder predicts the
    observation) or ``"hybrid"`` (:class:`pgm_wm.acrkn.HybridReadout`)."""
    _choice("readout", readout, ("difference", "absolute", "hybrid"))
    m = latent_obs_dim
    makers = {"mlp": lambda: MLPControl(action_dim, m, (hidden, hidden)),
              "linear": lambda: LinearControl(action_dim, m),
              "locally_linear": lambda: LocallyLinearControl(action_dim, m, num_basis)}
    ctrl = makers[_choice("control", control, tuple(makers))]()  # built first, as in the Chapter 4 notebook
    transition: nn.Module = LocallyLinearTransition(m, num_basis, bandwidth)
    if bounded:
        transition = NormBoundedTransition(transition, max_norm=1.0)
    head = (HybridReadout(obs_dim, diff_shift, diff_scale) if readout == "hybrid" else
            DifferenceReadout(obs_dim, readout == "difference", diff_shift, diff_scale))
    return AcRKN(ObservationEncoder(obs_dim, m, (hidden,)), transition, ctrl,
                 BeliefDecoder(m, head.decoder_dim, (hidden,), (hidden,)), readout=head)


def build_baseline(name: str, obs_dim: int = 2, action_dim: int = 2, hidden: int = 64, latent_obs_dim: int = 15,
                   num_basis: int = 15, bandwidth: int = 3, rnn_hidden: int | None = None,
                   **readout_kw: object) -> nn.Module:
    """A competitor with the world-model interface: ``"rkn_actions_as_obs"``, ``"lstm"``, ``"gru"``,
    ``"ffnn"`` (window 5) or ``"transformer"`` (Chapter 6's sizes). ``hidden`` is the MLP width,
    ``rnn_hidden`` the recurrent state (default ``hidden``); ``readout_kw`` (``diff_shift``,
    ``diff_scale``, ``predict_differences``) go to the feedback baselines' readout."""
    h, r = (hidden,), rnn_hidden or hidden
    makers = {
        "rkn_actions_as_obs": lambda: RKNActionsAsObs(obs_dim, action_dim, latent_obs_dim, num_basis, bandwidth, h, h,
                                                      **readout_kw),
        "lstm": lambda: LSTMBaseline(obs_dim, action_dim, r, h, h, **readout_kw),
        "gru": lambda: GRUBaseline(obs_dim, action_dim, r, h, h, **readout_kw),
        "ffnn": lambda: FFNNBaseline(obs_dim, action_dim, window=5, hidden=(hidden, hidden), **readout_kw),
        "transformer": lambda: TransformerBaseline(obs_dim, action_dim, d_model=32, n_heads=2, n_layers=2,
                                                   dim_feedforward=64),
    }
    return makers[_choice("name", name, tuple(makers))]()


# ----------------------------------------------------------------------------- Chapter 5
def build_hiprssm(obs_dim: int = 4, action_dim: int = 2, latent_obs_dim: int = 8, task_dim: int = 8,
                  hidden: int = 32, num_basis: int = 4, bandwidth: int = 2, task: str = "nonlinear",
                  encoder: str = "set", diff_shift: Vector = None, diff_scale: Vector = None,
                  readout: str = "difference") -> HiPRSSM:
    """The Chapter 5 HiP-RSSM: a Chapter 4 ac-RKN (width ``hidden``, ``readout`` as in
    :func:`build_acrkn`), a context encoder over interaction features of size
    ``2 obs_dim + action_dim`` (``"set"``: Bayesian aggregation, ``"recurrent"``: the ordered
    ablation) and a ``"nonlinear"`` or ``"linear"`` task term."""
    _choice("task", task, ("nonlinear", "linear"))
    _choice("encoder", encoder, ("set", "recurrent"))
    acrkn = build_acrkn(obs_dim, action_dim, latent_obs_dim, "mlp", False, hidden, num_basis, bandwidth,
                        diff_shift, diff_scale, readout)
    ctx = 2 * obs_dim + action_dim
    enc = (BayesianContextEncoder(ctx, task_dim, (hidden,)) if encoder == "set"
           else RecurrentContextEncoder(ctx, task_dim, (hidden,)))
    term = (NonlinearTaskTransform(task_dim, latent_obs_dim, (hidden,)) if task == "nonlinear"
            else LinearTaskTransform(task_dim, latent_obs_dim))
    return HiPRSSM(acrkn, enc, term)
