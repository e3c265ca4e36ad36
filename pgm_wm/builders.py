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

Saving and loading: :func:`save_model` writes the ``state_dict`` *and* the builder call that
made the model (every builder here records it on the model); :func:`load_model` rebuilds the
model from that call, or, given a model, refuses one built with another configuration (another
bandwidth, readout, MTS3 window, ``diagonal_only``, ...) instead of loading weights that fit its
shapes but mean something else. The file holds only tensors, strings and numbers, so it loads with
``torch.load``'s default ``weights_only=True``; predictions are bit-identical (tested in
``tests/test_fuzz_saving.py``)::

    save_model(model, "acrkn.pt")
    model = load_model("acrkn.pt")                        # rebuilt with the saved arguments

``torch.save(model, path)`` pickles the classes themselves, which ``torch.load``'s default
refuses to unpickle. A plain ``state_dict`` carries no configuration: it loads silently into any
model whose parameter shapes match.
"""

from __future__ import annotations

import functools
import inspect
import os
from typing import Any, Callable, Sequence, TypeVar

import torch
from torch import Tensor, nn

from .acrkn import (AcRKN, DifferenceReadout, HybridReadout, LinearControl, LocallyLinearControl, MLPControl,
                    NormBoundedTransition)
from .aggregation import BayesianContextEncoder, MaxPoolContextEncoder, MeanPoolContextEncoder
from .baselines import FFNNBaseline, GRUBaseline, LSTMBaseline, RKNActionsAsObs, TransformerBaseline
from .encoders import ConvTrunk
from .hiprssm import HiPRSSM, LinearTaskTransform, NonlinearTaskTransform, RecurrentContextEncoder
from .layers import GaussianHead
from . import mts3 as _mts3
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
    "save_model",
    "load_model",
    "builder_config",
]

_F = TypeVar("_F", bound=Callable[..., nn.Module])
_CONFIG_ATTR = "_pgm_wm_builder_config"
_FORMAT = "pgm_wm.save_model v1"
_BUILDERS: dict[str, Callable[..., nn.Module]] = {}


def _plain(value: Any) -> Any:
    """A copy of a builder argument made of tensors (detached, on the CPU), numbers, strings,
    None, tuples, lists and dicts, which ``torch.load(weights_only=True)`` reads back."""
    if isinstance(value, Tensor):
        return value.detach().cpu().clone()
    if isinstance(value, (list, tuple)):
        return type(value)(_plain(v) for v in value) if isinstance(value, tuple) else [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise ValueError(f"builder argument: {type(value).__name__} values cannot be saved with the model")


def _recorded(fn: _F) -> _F:
    """Register a builder and make it record its call (name and every argument, defaults
    included) on the model it returns, for :func:`save_model`."""
    signature = inspect.signature(fn)

    @functools.wraps(fn)
    def build(*args: Any, **kwargs: Any) -> nn.Module:
        bound = signature.bind(*args, **kwargs)
        bound.apply_defaults()
        config: dict[str, Any] = {}
        for name, value in bound.arguments.items():
            if signature.parameters[name].kind is inspect.Parameter.VAR_KEYWORD:
                config.update(value)
            else:
                config[name] = value
        model = fn(*args, **kwargs)
        object.__setattr__(model, _CONFIG_ATTR, {"builder": fn.__name__, "kwargs": _plain(config)})
        return model

    _BUILDERS[fn.__name__] = build
    return build  # type: ignore[return-value]


def builder_config(model: nn.Module) -> dict[str, Any] | None:
    """``{"builder": name, "kwargs": {...}}`` of a model made by a builder of this module, else ``None``."""
    return getattr(model, _CONFIG_ATTR, None)

Vector = Tensor | Sequence[float] | None


def _choice(name: str, value: str, options: Sequence[str]) -> str:
    if value not in options:
        raise ValueError(f"{name}: expected one of {tuple(options)}, got {value!r}")
    return value


# ----------------------------------------------------------------------------- Chapter 2
@_recorded
def build_set_model(kind: str, in_dim: int, latent_dim: int = 1, hidden: Sequence[int] = (64, 64)) -> nn.Module:
    """A set model ``model(x, mask) -> (mean, var)``: ``kind`` = ``"bayesian"`` (Bayesian
    aggregation, Eq. ba-update), ``"mean"`` or ``"max"`` (deep-set pooling baselines)."""
    cls = {"bayesian": BayesianContextEncoder, "mean": MeanPoolContextEncoder, "max": MaxPoolContextEncoder}
    return cls[_choice("kind", kind, tuple(cls))](in_dim, latent_dim, hidden=hidden)


# ----------------------------------------------------------------------------- Chapter 3
@_recorded
def build_image_encoder(image_shape: Sequence[int], latent_obs_dim: int = 8, channels: Sequence[int] = (8, 16),
                        feature_dim: int = 32) -> ObservationEncoder:
    """The pendulum encoder: :class:`pgm_wm.encoders.ConvTrunk` then the latent-observation heads."""
    if len(image_shape) != 2:
        raise ValueError(f"image_shape: expected (H, W), got {tuple(image_shape)}")
    H, W = image_shape
    return ObservationEncoder(H * W, latent_obs_dim, trunk=ConvTrunk(image_shape, channels=channels,
                                                                      feature_dim=feature_dim),
                              feature_dim=feature_dim)


@_recorded
def build_rkn(image_shape: Sequence[int], out_dim: int = 2, latent_obs_dim: int = 8, num_basis: int = 15,
              bandwidth: int = 3, decoder_hidden: Sequence[int] = (32,), diagonal_only: bool = False) -> RKN:
    """The Chapter 3 RKN on images (``diagonal_only=True``: the diagonal-covariance ablation)."""
    return RKN(build_image_encoder(image_shape, latent_obs_dim),
               LocallyLinearTransition(latent_obs_dim, num_basis, bandwidth),
               BeliefDecoder(latent_obs_dim, out_dim, decoder_hidden, decoder_hidden, log_var_input=True),
               diagonal_only=diagonal_only)


@_recorded
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
@_recorded
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


@_recorded
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
@_recorded
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


# ----------------------------------------------------------------------------- Chapter 6 (defined in pgm_wm.mts3)
build_fast_acrkn = _recorded(_mts3.build_fast_acrkn)
build_mts3 = _recorded(_mts3.build_mts3)
build_hierarchical_mts3 = _recorded(_mts3.build_hierarchical_mts3)


# ----------------------------------------------------------------------------- saving and loading
def save_model(model: nn.Module, path: str | os.PathLike) -> None:
    """Write ``model``'s ``state_dict`` together with the builder call that made it (written to a
    temporary file, then renamed into place). ``model`` must come from a builder of this module."""
    config = builder_config(model) if isinstance(model, nn.Module) else None
    if config is None:
        raise ValueError("model: not made by a builder of pgm_wm.builders, so its configuration is unknown; "
                         "build it with pgm_wm.builders.build_* (or save its state_dict yourself)")
    state = {"format": _FORMAT, "builder": config["builder"], "kwargs": config["kwargs"],
             "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()}}
    target = os.fspath(path)
    tmp = target + ".tmp"
    torch.save(state, tmp)
    os.replace(tmp, target)


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, Tensor) or isinstance(b, Tensor):
        return isinstance(a, Tensor) and isinstance(b, Tensor) and a.shape == b.shape and bool(torch.equal(a, b))
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return type(a) is type(b) and a == b or (isinstance(a, (int, float)) and isinstance(b, (int, float))
                                            and not isinstance(a, bool) and not isinstance(b, bool) and a == b)


def load_model(path: str | os.PathLike, model: nn.Module | None = None) -> nn.Module:
    """Read a file of :func:`save_model`. Without ``model``: rebuild the model with the saved
    builder call and load the weights. With ``model``: check that it was built by the same builder
    with the same arguments (else ``ValueError`` naming every difference), then load the weights
    into it. Returns the model in eval mode."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # a damaged or foreign file: say which
        raise ValueError(f"path: {path} cannot be read as a saved pgm_wm model ({type(err).__name__}: {err})") from err
    if not isinstance(state, dict) or state.get("format") != _FORMAT:
        raise ValueError(f"path: {path} is not a file written by pgm_wm.builders.save_model (a plain state_dict "
                         f"carries no configuration; load it with model.load_state_dict)")
    name, kwargs = state["builder"], state["kwargs"]
    if name not in _BUILDERS:
        raise ValueError(f"path: {path} was saved from an unknown builder {name!r}")
    if model is None:
        model = _BUILDERS[name](**kwargs)
    else:
        have = builder_config(model)
        if have is None:
            raise ValueError("model: not made by a builder of pgm_wm.builders, so it cannot be checked against "
                             f"the saved configuration ({name}); call load_model(path) to rebuild it")
        if have["builder"] != name:
            raise ValueError(f"model: built by {have['builder']}, the file was saved from a {name} model")
        diffs = [f"{k}={have['kwargs'].get(k)!r} (saved {kwargs.get(k)!r})"
                 for k in sorted(set(kwargs) | set(have["kwargs"])) if not _same(have["kwargs"].get(k), kwargs.get(k))]
        if diffs:
            raise ValueError(f"model: built with another configuration than the saved {name} model: "
                             + ", ".join(diffs))
    try:
        model.load_state_dict(state["state_dict"])
    except RuntimeError as err:
        raise ValueError(f"path: the saved weights do not fit the model ({err})") from err
    return model.eval()
