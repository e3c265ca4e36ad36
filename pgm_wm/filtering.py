r"""The one result type of every filter in the book (Chapters 1, 3–6).

Every filter, dense (:func:`pgm_wm.kalman.kalman_filter`) or factorized (the RKN family), runs
the same loop over :math:`t = 1..T`: *update* the prior of step :math:`t` with the observation
:math:`y_t` (skipped where it is missing), then *predict* the prior of step :math:`t+1`. Its
output is a :class:`FilterResult` whose fields mean the same thing in every chapter:

* ``prior[..., t]``      :math:`p(z_t \mid y_{<t})`       (before the update at step ``t``);
* ``posterior[..., t]``  :math:`p(z_t \mid y_{\le t})`    (after it; equal to ``prior`` where masked);
* ``next_prior[..., t]`` :math:`p(z_{t+1} \mid y_{\le t})` (the prediction made at step ``t``;
  ``next_prior[..., t] = prior[..., t + 1]`` and ``next_prior[..., T-1]`` is the one-step-ahead
  prediction past the end);
* ``log_likelihoods[..., t]`` :math:`\log p(y_t \mid y_{<t})` where the model defines it
  (the dense Kalman filter, Eq. kf-loglik), ``None`` otherwise; 0 at missing steps.

Beliefs are stacked along a time axis just before their event axes (``mean: (..., T, n)``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Generic, TypeVar

from torch import Tensor

__all__ = ["FilterResult", "filter_loop"]

BeliefT = TypeVar("BeliefT")


@dataclass(frozen=True)
class FilterResult(Generic[BeliefT]):
    """Beliefs of one filter run over ``T`` steps, see the module docstring for each field."""

    prior: BeliefT
    posterior: BeliefT
    next_prior: BeliefT
    log_likelihoods: Tensor | None = None

    @property
    def log_likelihood(self) -> Tensor:
        r"""Total :math:`\log p(y_{1:T}) = \sum_t \log p(y_t \mid y_{<t})`, shape ``(...)``."""
        if self.log_likelihoods is None:
            raise ValueError("log_likelihoods: this filter does not define an exact log-likelihood")
        return self.log_likelihoods.sum(-1)

    def map(self, fn: Any) -> "FilterResult[BeliefT]":
        """Apply ``fn`` to each of the three beliefs (and keep ``log_likelihoods``)."""
        return FilterResult(fn(self.prior), fn(self.posterior), fn(self.next_prior), self.log_likelihoods)


def filter_loop(
    prior: Any,
    update: Callable[[Any, Any, Tensor | None], Any],
    predict: Callable[[Any, int], Any],
    observations: Any,
    mask: Tensor | None = None,
) -> FilterResult:
    r"""The book's filter loop, written once: for :math:`t = 1..T`, *update* then *predict*.

    .. math:: p(z_t\mid y_{\le t}) \propto p(y_t\mid z_t)\,p(z_t\mid y_{<t}),\qquad
              p(z_{t+1}\mid y_{\le t}) = \int p(z_{t+1}\mid z_t)\,p(z_t\mid y_{\le t})\,dz_t,

    i.e. Eq. (kf-update) then Eq. (kf-predict) for the dense filter and Eq. (rkn-update) then
    Eq. (rkn-predict) for the factorized ones. This is the readable reference: every fast
    backend is tested equal to a filter built on it.

    Args:
        prior: belief of the first step, :math:`p(z_1)`, batch ``(...)``.
        update: ``(prior_t, observation_t, mask_t | None) -> posterior_t`` (posterior = prior where
            ``mask_t`` is False).
        predict: ``(posterior_t, t) -> prior_{t+1}`` (``t`` selects known inputs of that step).
        observations: a belief stacked over time (e.g. a :class:`pgm_wm.beliefs.DiagGaussian`
            with ``mean: (..., T, m)``); ``observations.at(t)`` is step ``t``.
        mask: ``(..., T)`` bool, True = observed, or ``None`` (all observed).

    Returns the :class:`FilterResult` (``log_likelihoods=None``).
    """
    T = observations.mean.shape[-2]
    if T == 0:
        raise ValueError("observations: need at least one time step, got T = 0")
    priors, posteriors, next_priors = [], [], []
    for t in range(T):
        posterior = update(prior, observations.at(t), None if mask is None else mask[..., t])
        next_prior = predict(posterior, t)
        priors.append(prior)
        posteriors.append(posterior)
        next_priors.append(next_prior)
        prior = next_prior
    stack = type(prior).stack
    return FilterResult(stack(priors), stack(posteriors), stack(next_priors))
