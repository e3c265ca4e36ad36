r"""Evaluation metrics and (de)normalization shared by the model chapters (4, 5, 6).

* :func:`rmse` — root mean squared error over the selected entries, Eq. (metric-rmse).
* :func:`gaussian_nll` — negative log-likelihood of a diagonal Gaussian prediction,
  **averaged per dimension** and including the constant :math:`\tfrac12\log 2\pi`,
  Eq. (metric-nll):

  .. math:: \mathrm{NLL} = \frac{1}{N}\sum_{i}\tfrac12\Big(\log 2\pi + \log\sigma_i^2
            + \frac{(y_i-\mu_i)^2}{\sigma_i^2}\Big),

  the sum running over the :math:`N` selected (time step, dimension) entries. Lower is better.
* :func:`interval_coverage` — calibration: the share of the selected entries that fall inside the
  central band :math:`\mu_i \pm z\sigma_i` of their prediction, Eq. (metric-coverage); a
  calibrated Gaussian prediction covers :func:`nominal_coverage` :math:`= \operatorname{erf}(z/\sqrt2)`
  of them (0.954 for :math:`z = 2`), an over-confident one less, an under-confident one more.
* :func:`normalize` / :func:`denormalize` / :func:`denormalize_var`: map data to and from the
  units the models see, with training-split statistics. Denormalizing the prediction before
  computing a metric gives it in original units (e.g. radians); for the NLL this adds
  :math:`\overline{\log s}` (the mean log standard deviation of the selected dimensions).

Masks: ``mask`` may have the shape of ``pred`` or of its leading dimensions (e.g. ``(B, T)``
for ``pred: (B, T, d)``); True = include. ``dim=None`` reduces over everything; otherwise over
the given dimensions (e.g. ``dim=(0, 2)`` gives one value per time step).

Chapter 6 appends sliding-window versions at the end of this file.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor

from ._checks import as_tensor, check_finite, check_positive, check_same_dtype, check_tensor

__all__ = [
    "rmse",
    "gaussian_nll",
    "interval_coverage",
    "nominal_coverage",
    "normalize",
    "denormalize",
    "denormalize_var",
]

Dims = int | Sequence[int] | None


def _weights(name: str, mask: Tensor | None, like: Tensor) -> Tensor:
    """Expand a mask with the shape of ``like`` or of its leading dims into float weights."""
    if mask is None:
        return torch.ones_like(like)
    if not isinstance(mask, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(mask).__name__}")
    if mask.ndim > like.ndim or tuple(mask.shape) != tuple(like.shape[: mask.ndim]):
        raise ValueError(f"{name}: expected shape {tuple(like.shape)} or a prefix of it, got {tuple(mask.shape)}")
    if mask.dtype != torch.bool:
        if not bool(((mask == 0) | (mask == 1)).all()):
            raise ValueError(f"{name}: a mask must contain only 0/1 or True/False")
    m = mask.to(like.dtype).reshape(*mask.shape, *([1] * (like.ndim - mask.ndim)))
    return m.expand_as(like)


def _reduce(values: Tensor, weights: Tensor, dim: Dims) -> Tensor:
    total = weights.sum() if dim is None else weights.sum(dim)
    if bool((total == 0).any()):
        raise ValueError("mask: selects no entries (in some slice being averaged)")
    s = (values * weights).sum() if dim is None else (values * weights).sum(dim)
    return s / total


def _check_pair(pred: Tensor, target: Tensor, pred_name: str = "pred") -> None:
    check_tensor(pred_name, pred)
    check_tensor("target", target)
    check_same_dtype((pred_name, "target"), (pred, target))
    if pred.shape != target.shape:
        raise ValueError(f"target: shape {tuple(target.shape)} differs from {pred_name}'s {tuple(pred.shape)}")


def rmse(pred: Tensor, target: Tensor, mask: Tensor | None = None, dim: Dims = None) -> Tensor:
    r"""Root mean squared error, Eq. (metric-rmse): :math:`\sqrt{\frac1N\sum_i (\hat y_i - y_i)^2}`
    over the entries selected by ``mask``, reduced over ``dim`` (all by default)."""
    _check_pair(pred, target)
    w = _weights("mask", mask, pred)
    return _reduce((pred - target) ** 2, w, dim).sqrt()


def gaussian_nll(mean: Tensor, var: Tensor, target: Tensor, mask: Tensor | None = None, dim: Dims = None) -> Tensor:
    r"""Per-dimension average Gaussian negative log-likelihood, Eq. (metric-nll), with
    :math:`\tfrac12\log 2\pi` included. ``var`` must be positive. Same masks/dims as :func:`rmse`."""
    terms, w = _nll_terms(mean, var, target), _weights("mask", mask, mean)
    check_finite("target", target.detach()[w.detach() > 0])
    return _reduce(terms, w, dim)


def interval_coverage(mean: Tensor, var: Tensor, target: Tensor, z: float = 2.0, mask: Tensor | None = None,
                      dim: Dims = None) -> Tensor:
    r"""Share of the selected entries inside the central band of their Gaussian prediction,
    Eq. (metric-coverage): :math:`\frac1N\sum_i \mathbb 1\big[|y_i - \mu_i| \le z\,\sigma_i\big]`.
    Compare with :func:`nominal_coverage` (``z = 2``: 0.954). ``var`` must be positive, ``z`` > 0;
    same masks/dims as :func:`rmse`."""
    if not (isinstance(z, (int, float)) and not isinstance(z, bool) and math.isfinite(z) and z > 0):
        raise ValueError(f"z: must be a positive finite number, got {z!r}")
    _nll_terms(mean, var, target)                      # the same checks as the NLL
    w = _weights("mask", mask, mean)
    check_finite("target", target.detach()[w.detach() > 0])
    inside = ((target - mean).abs() <= z * var.sqrt()).to(mean.dtype)
    return _reduce(inside, w, dim)


def nominal_coverage(z: float = 2.0) -> float:
    r""":math:`P(|Z| \le z) = \operatorname{erf}(z/\sqrt 2)` for a standard normal :math:`Z`: the
    coverage Eq. (metric-coverage) of a calibrated Gaussian prediction."""
    if not (isinstance(z, (int, float)) and not isinstance(z, bool) and math.isfinite(z) and z > 0):
        raise ValueError(f"z: must be a positive finite number, got {z!r}")
    return math.erf(z / math.sqrt(2.0))


def _nll_terms(mean: Tensor, var: Tensor, target: Tensor) -> Tensor:
    """Validated elementwise terms :math:`\\tfrac12[\\log 2\\pi\\sigma + (y-\\mu)^2/\\sigma]`."""
    _check_pair(mean, target, "mean")
    check_tensor("var", var)
    if var.shape != mean.shape:
        raise ValueError(f"var: shape {tuple(var.shape)} differs from mean's {tuple(mean.shape)}")
    check_same_dtype(("mean", "var"), (mean, var))
    check_positive("var", var.detach())
    check_finite("mean", mean.detach())
    return 0.5 * (math.log(2 * math.pi) + var.log() + (target - mean) ** 2 / var)


def _stat(name: str, x: object, like: Tensor) -> Tensor:
    t = as_tensor(name, x).to(dtype=like.dtype, device=like.device)
    if t.ndim > 1 or (t.ndim == 1 and t.shape[0] != like.shape[-1]):
        raise ValueError(f"{name}: expected a scalar or shape ({like.shape[-1]},), got {tuple(t.shape)}")
    return t


def normalize(x: Tensor, mean: object, std: object) -> Tensor:
    """``(x - mean) / std`` over the last dimension; ``std`` must be positive."""
    check_tensor("x", x, 1)
    mu, s = _stat("mean", mean, x), _stat("std", std, x)
    if not bool((s > 0).all()):
        raise ValueError("std: must be positive")
    return (x - mu) / s


def denormalize(x: Tensor, mean: object, std: object) -> Tensor:
    """Inverse of :func:`normalize`: ``x * std + mean``."""
    check_tensor("x", x, 1)
    mu, s = _stat("mean", mean, x), _stat("std", std, x)
    if not bool((s > 0).all()):
        raise ValueError("std: must be positive")
    return x * s + mu


def denormalize_var(var: Tensor, std: object) -> Tensor:
    """Variance in original units: ``var * std**2``."""
    check_tensor("var", var, 1)
    s = _stat("std", std, var)
    if not bool((s > 0).all()):
        raise ValueError("std: must be positive")
    return var * s * s


# ----------------------------------------------------------------------------- Chapter 6: sliding windows
__all__ += ["sliding_window_rmse", "sliding_window_nll"]


def _sliding_mean(per_entry: Tensor, weights: Tensor, window: int) -> Tensor:
    """Weighted mean of ``per_entry: (B, T, ...)`` over the batch, the trailing dimensions and the
    time steps ``max(0, t - window + 1) .. t`` for every ``t``: returns ``(T,)``."""
    dims = [0] + list(range(2, per_entry.ndim))
    trailing = lambda x: torch.cat([x.new_zeros(window - 1), x]).unfold(0, window, 1).sum(-1)  # noqa: E731
    s_w = trailing((per_entry * weights).sum(dims))
    n_w = trailing(weights.sum(dims))
    if bool((n_w <= 0).any()):
        raise ValueError("mask: some sliding window selects no entries")
    return s_w / n_w


def _check_window(window: int, pred: Tensor) -> None:
    if pred.ndim < 2:
        raise ValueError(f"pred: expected (B, T, ...), got shape {tuple(pred.shape)}")
    if not isinstance(window, int) or window <= 0:
        raise ValueError(f"window: must be a positive int, got {window!r}")


def sliding_window_rmse(pred: Tensor, target: Tensor, window: int, mask: Tensor | None = None) -> Tensor:
    r"""Sliding-window RMSE over a prediction horizon, Eq. (metric-sliding-rmse):

    .. math:: \mathrm{RMSE}(t) = \sqrt{\frac{1}{N_t}\sum_{b}\sum_{i=t-W+1}^{t}\sum_{j}
              \big(\hat y_{b,i,j} - y_{b,i,j}\big)^2},

    the mean running over sequences :math:`b`, the last :math:`W` = ``window`` time steps up to and
    including :math:`t`, and the dimensions :math:`j` (:math:`N_t` entries; the first
    :math:`W-1` windows are shorter). ``pred, target: (B, T, ...)``, ``mask`` as in :func:`rmse`.
    Returns ``(T,)``. Denormalize first to get it in original units.
    """
    _check_pair(pred, target)
    _check_window(window, pred)
    w = _weights("mask", mask, pred)
    return _sliding_mean((pred - target) ** 2, w, window).sqrt()


def sliding_window_nll(mean: Tensor, var: Tensor, target: Tensor, window: int, mask: Tensor | None = None) -> Tensor:
    r"""Sliding-window Gaussian NLL, Eq. (metric-sliding-nll): the per-dimension NLL of
    :func:`gaussian_nll` averaged over sequences, dimensions and the last ``window`` steps up to
    and including ``t`` (shorter windows at the start). ``mean, var, target: (B, T, ...)``.
    Returns ``(T,)``. (The thesis sums the log-density over dimensions; we average, as
    :func:`gaussian_nll` does — multiply by the number of dimensions to compare.)
    """
    per = _nll_terms(mean, var, target)
    _check_window(window, mean)
    return _sliding_mean(per, _weights("mask", mask, mean), window)
