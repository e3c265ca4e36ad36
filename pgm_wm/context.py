r"""Context sets of transitions, and fitting a set model to infer a hidden parameter (Chapter 2).

A *context set* is an unordered collection of transitions :math:`x_n = [o_t, a_t, o_{t+1} - o_t]`
drawn from one sequence whose hidden parameter (e.g. a payload mass) is constant. A set model
(:class:`pgm_wm.aggregation.BayesianContextEncoder` or a deep-set baseline) maps the set to a
Gaussian belief over the parameter and is trained by the Gaussian negative log-likelihood
(Eq. (ba-nll)) of the true value.

* :func:`transition_features` builds the per-step elements from ``obs`` and ``actions``
  (:func:`normalized_transition_features` for a dataset split, normalized with training stats);
* :class:`ContextSetSampler` draws batches of padded sets of random size (``mask`` marks
  the present elements), optionally corrupting a random fraction of the elements;
* :func:`set_nll`, :func:`fit_set_model`, :func:`evaluate_set_model`: loss, training (the
  package's :func:`pgm_wm.training.fit` with validation-based model selection), and metrics.

The HiP-RSSM chapter reuses the sampler idea with the context taken from the recent past.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from ._checks import check_tensor
from .datasets.windows import transition_features
from .metrics import gaussian_nll
from .training import FitHistory, fit

__all__ = [
    "transition_features",
    "normalized_transition_features",
    "ContextBatch",
    "ContextSetSampler",
    "corrupt_elements",
    "set_nll",
    "fit_set_model",
    "evaluate_set_model",
]


def normalized_transition_features(data: Any) -> Tensor:
    r"""Transition elements of a :class:`pgm_wm.datasets.SequenceData` split, each part normalized
    with the *training* statistics: :math:`[\bar o_t, \bar a_t, \overline{o_{t+1}-o_t}]`,
    ``(n, T-1, 2 d_obs + d_act)``. Requires actions and fully observed sequences.
    """
    if data.actions is None:
        raise ValueError("data: the dataset has no actions")
    if not bool(data.valid.all()):
        raise ValueError("data: transition features need fully observed sequences")
    obs, act = data.obs, data.actions
    diff = data.normalize_diff(obs[:, 1:] - obs[:, :-1])
    return torch.cat([data.normalize_obs(obs[:, :-1]), data.normalize_actions(act[:, :-1]), diff], dim=-1)


@dataclass
class ContextBatch:
    """A batch of padded context sets.

    Attributes:
        x: ``(B, N_max, F)`` set elements (padded entries hold real but unused transitions).
        mask: ``(B, N_max)`` bool, True = element present.
        y: ``(B, k)`` targets (the hidden parameter of each set's sequence).
        seq: ``(B,)`` index of the sequence each set was drawn from.
        corrupted: ``(B, N_max)`` bool, True = element was replaced by junk.
        level: ``(B, N_max)`` noise scale added to each element (0 = clean).
    """

    x: Tensor
    mask: Tensor
    y: Tensor
    seq: Tensor
    corrupted: Tensor
    level: Tensor

    @property
    def sizes(self) -> Tensor:
        """Number of present elements per set, ``(B,)``."""
        return self.mask.sum(-1)


def corrupt_elements(
    x: Tensor, frac: Tensor | float, scale: Tensor | float, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    r"""Corrupt a random fraction of set elements: :math:`x_n \leftarrow x_n + s\,\varepsilon_n`,
    :math:`\varepsilon_n\sim\mathcal N(0, I)`, for each element independently with probability
    ``frac`` (per set, ``(B,)`` or scalar); ``scale`` is :math:`s` (scalar, ``(B,)`` or ``(B, N)``).

    Returns ``(x_corrupted, corrupted: (B, N) bool, level: (B, N))``.
    """
    check_tensor("x", x, min_ndim=3)
    B, N, _ = x.shape
    frac = torch.as_tensor(frac, dtype=x.dtype)
    scale = torch.as_tensor(scale, dtype=x.dtype)
    if bool((frac < 0).any()) or bool((frac > 1).any()):
        raise ValueError("frac: must lie in [0, 1]")
    if bool((scale < 0).any()):
        raise ValueError("scale: must be >= 0")
    frac = frac.reshape(-1, 1) if frac.ndim == 1 else frac
    scale = scale.reshape(-1, 1) if scale.ndim == 1 else scale
    u = torch.rand(B, N, generator=generator, dtype=x.dtype)
    corrupted = u < frac
    level = torch.where(corrupted, scale.expand(B, N), torch.zeros(B, N, dtype=x.dtype))
    eps = torch.randn(x.shape, generator=generator, dtype=x.dtype)
    return x + level.unsqueeze(-1) * eps, corrupted, level


class ContextSetSampler:
    r"""Draws context sets from sequences with a constant hidden parameter.

    Args:
        features: ``(S, T, F)`` per-step elements of ``S`` sequences (e.g. from
            :func:`transition_features`).
        targets: ``(S, k)`` the hidden parameter of each sequence (constant over time).

    Each set takes ``N`` distinct random time steps of one random sequence (without replacement,
    so ``N <= T``).
    """

    def __init__(self, features: Tensor, targets: Tensor) -> None:
        check_tensor("features", features, min_ndim=3)
        check_tensor("targets", targets, min_ndim=2)
        if features.ndim != 3 or targets.ndim != 2:
            raise ValueError(f"features: expected (S, T, F) and targets (S, k), got "
                             f"{tuple(features.shape)} and {tuple(targets.shape)}")
        if targets.shape[0] != features.shape[0]:
            raise ValueError(f"targets: {targets.shape[0]} rows, features has {features.shape[0]} sequences")
        self.features, self.targets = features, targets

    @classmethod
    def from_sequence_data(
        cls, data: Any, hidden_key: str = "payload", target_mean: float = 0.0, target_std: float = 1.0
    ) -> "ContextSetSampler":
        r"""Build a sampler from a :class:`pgm_wm.datasets.SequenceData` split.

        Elements: :func:`normalized_transition_features`. Target: ``data.hidden[hidden_key]``
        (``(S, T)`` or ``(S, T, k)``), which must be constant within each sequence, normalized as
        ``(value - target_mean) / target_std`` (pass *training-split* statistics).
        """
        if target_std <= 0:
            raise ValueError(f"target_std: must be > 0, got {target_std}")
        if hidden_key not in data.hidden:
            raise ValueError(f"hidden_key: {hidden_key!r} not in data.hidden ({sorted(data.hidden)})")
        h = data.hidden[hidden_key]
        h = h.unsqueeze(-1) if h.ndim == 2 else h
        if not bool((h == h[:, :1]).all()):
            raise ValueError(f"hidden_key: {hidden_key!r} is not constant within each sequence")
        y = (h[:, 0].to(torch.get_default_dtype()) - target_mean) / target_std
        return cls(normalized_transition_features(data), y)

    @property
    def n_sequences(self) -> int:
        return self.features.shape[0]

    @property
    def n_steps(self) -> int:
        return self.features.shape[1]

    def sample(
        self,
        n_sets: int,
        n_max: int,
        n_min: int | None = None,
        generator: torch.Generator | None = None,
        corrupt_frac: float | Tensor = 0.0,
        corrupt_scale: float | Tensor = 0.0,
        seq: Tensor | None = None,
        sizes: Tensor | None = None,
    ) -> ContextBatch:
        """Sample ``n_sets`` sets padded to ``n_max`` elements.

        Set sizes are uniform on ``{n_min, ..., n_max}`` (``n_min=None`` -> all sets have
        ``n_max`` elements). ``corrupt_frac`` / ``corrupt_scale`` (scalars or ``(n_sets,)``) are
        passed to :func:`corrupt_elements`. ``seq`` fixes which sequence each set comes from;
        ``sizes`` (``(n_sets,)`` ints in ``[1, n_max]``) fixes the set sizes instead.
        """
        if not 1 <= n_max <= self.n_steps:
            raise ValueError(f"n_max: must be in [1, {self.n_steps}], got {n_max}")
        n_min = n_max if n_min is None else n_min
        if not 1 <= n_min <= n_max:
            raise ValueError(f"n_min: must be in [1, n_max={n_max}], got {n_min}")
        if seq is None:
            seq = torch.randint(self.n_sequences, (n_sets,), generator=generator)
        elif tuple(seq.shape) != (n_sets,):
            raise ValueError(f"seq: expected shape ({n_sets},), got {tuple(seq.shape)}")
        # N distinct steps per set: the first n_max entries of a random permutation.
        steps = torch.rand(n_sets, self.n_steps, generator=generator).argsort(-1)[:, :n_max]
        x = self.features[seq.unsqueeze(-1), steps]
        if sizes is None:
            sizes = torch.randint(n_min, n_max + 1, (n_sets,), generator=generator)
        elif tuple(sizes.shape) != (n_sets,) or bool((sizes < 1).any()) or bool((sizes > n_max).any()):
            raise ValueError(f"sizes: expected ({n_sets},) integers in [1, {n_max}]")
        mask = torch.arange(n_max).unsqueeze(0) < sizes.unsqueeze(-1)
        x, corrupted, level = corrupt_elements(x, corrupt_frac, corrupt_scale, generator)
        return ContextBatch(x, mask, self.targets[seq], seq, corrupted & mask, level * mask)


def set_nll(y: Tensor, mean: Tensor, var: Tensor) -> Tensor:
    r"""Gaussian negative log-likelihood of each set's target, summed over its ``k`` dimensions,
    Eq. (ba-nll): :math:`\tfrac12\sum_i[\log 2\pi\sigma_i + (y_i-\mu_i)^2/\sigma_i]`.

    Shapes ``(..., k)`` -> ``(...)``; ``var`` must be positive. It is ``k`` times the
    per-dimension average :func:`pgm_wm.metrics.gaussian_nll`.
    """
    check_tensor("y", y, 1)
    return gaussian_nll(mean, var, y, dim=-1) * y.shape[-1]


def fit_set_model(
    model: nn.Module,
    sampler: ContextSetSampler,
    valid: ContextBatch,
    steps: int = 1000,
    batch_size: int = 64,
    n_max: int = 64,
    n_min: int = 1,
    lr: float = 3e-3,
    corrupt_prob: float = 0.5,
    corrupt_frac_max: float = 0.5,
    corrupt_scale_max: float = 3.0,
    eval_every: int = 50,
    clip: float = 5.0,
    seed: int = 0,
    *,
    budget_s: float | None = None,
    patience: int | None = None,
    progress: bool | None = False,
) -> FitHistory:
    r"""Train ``model(x, mask) -> (mean, var)`` by the Gaussian NLL of the set's target, Eq. (ba-nll).

    Each step draws ``batch_size`` sets with sizes uniform on ``{n_min..n_max}``. A fraction
    ``corrupt_prob`` of the sets is corrupted (:func:`corrupt_elements`): each of their elements
    with probability ``U(0, corrupt_frac_max)`` gets Gaussian noise of scale
    ``U(0, corrupt_scale_max)`` (per element). The loop is :func:`pgm_wm.training.fit` with this
    sampler: one "epoch" is ``eval_every`` steps, after which the validation NLL on the fixed
    batch ``valid`` is recorded; the weights of the best validation epoch are restored (model
    selection on the validation split only). ``steps`` caps the number of steps (rounded up to
    whole epochs), ``budget_s`` (CPU seconds) and ``patience`` (epochs) stop earlier. The optimizer
    step of each epoch's end is ``history.steps``.
    """
    if not isinstance(eval_every, int) or eval_every <= 0:
        raise ValueError(f"eval_every: must be a positive int, got {eval_every!r}")
    if not isinstance(steps, int) or steps <= 0:
        raise ValueError(f"steps: must be a positive int, got {steps!r}")

    def sample(gen: torch.Generator) -> ContextBatch:
        hit = torch.rand(batch_size, generator=gen) < corrupt_prob
        frac = torch.where(hit, torch.rand(batch_size, generator=gen) * corrupt_frac_max, torch.zeros(batch_size))
        scale = torch.rand(batch_size, n_max, generator=gen) * corrupt_scale_max
        return sampler.sample(batch_size, n_max, n_min, gen, frac, scale)

    def loss_fn(batch: ContextBatch, gen: torch.Generator) -> Tensor:
        mean, var = model(batch.x, batch.mask)
        return set_nll(batch.y, mean, var).mean()

    return fit(loss_fn, model, sample, batch_size, epochs=-(-steps // eval_every), lr=lr, clip_norm=clip, seed=seed,
               valid_fn=lambda: evaluate_set_model(model, valid)["nll"], progress=progress,
               max_batches=eval_every, desc="fit_set_model", budget_s=budget_s, patience=patience)


@torch.no_grad()
def evaluate_set_model(model: nn.Module, batch: ContextBatch, target_scale: float = 1.0) -> dict[str, float]:
    r"""RMSE and mean Gaussian NLL of ``model`` on ``batch``.

    ``target_scale`` converts normalized targets back to physical units
    (:math:`y = \text{mean} + \text{scale}\cdot y_n`): RMSE is multiplied by it and the NLL gets
    :math:`+k\log(\text{scale})` (the Jacobian), so both are reported in physical units.
    """
    if target_scale <= 0:
        raise ValueError(f"target_scale: must be > 0, got {target_scale}")
    was_training = model.training
    model.eval()
    mean, var = model(batch.x, batch.mask)
    model.train(was_training)
    k = batch.y.shape[-1]
    rmse = float(((mean - batch.y) ** 2).mean().sqrt()) * target_scale
    nll = float(set_nll(batch.y, mean, var).mean()) + k * math.log(target_scale)
    return {"rmse": rmse, "nll": nll, "std": float(var.sqrt().mean()) * target_scale}
