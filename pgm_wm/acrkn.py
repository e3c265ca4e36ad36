r"""The action-conditional RKN (Chapter 4): a single-time-scale probabilistic world model.

The ac-RKN is the RKN of Chapter 3 with **one additive term** in the predict step. Given the
posterior :math:`\mathcal N(z_t^+, \Sigma_t^+)` and the executed action :math:`a_t`, the prior of
the next step is the marginal of :math:`z_{t+1} = A_t z_t + b(a_t, z_t^+) + \varepsilon_t`,
Eq. (acrkn-predict):

.. math:: z^-_{t+1} = A_t z^+_t + b(a_t),\qquad \Sigma^-_{t+1} = A_t\Sigma^+_tA_t^\top + Q.

The action is known, so it is a cause with zero variance (Eq. gauss-marginal with
:math:`\Sigma_a = 0`): it moves the mean and leaves the covariance — and therefore the Kalman
gain — untouched (:func:`pgm_wm.factorized.known_input`). Because the locally linear
:math:`A_t` depends on the posterior *mean*, a different action history changes later
covariances indirectly; with a state-independent :math:`A` (``num_basis=1``) the covariances of
a whole run do not depend on the actions at all.

Control models :math:`b` (all share ``forward(action (..., da), mean (..., 2m)) -> (..., 2m)``):

* :class:`LinearControl`        :math:`b(a) = B a`;
* :class:`LocallyLinearControl` :math:`b(a, z) = \sum_k \beta_k(z) B^{(k)} a`, softmax coefficients;
* :class:`MLPControl`           :math:`b(a) = f(a)`, an MLP (the thesis' default);
* :class:`ZeroControl`          :math:`b = 0` (the ac-RKN then *is* the RKN — a test).

Prediction convention (:class:`AcRKN.forward`). Index ``t`` of the output is the prediction of
:math:`o_{t+1}` from the observed :math:`o_{\le t}` and the actions :math:`a_{\le t}`; it is the
decoded prior :math:`p(z_{t+1}\mid w_{\le t}, a_{\le t})`. With ``predict_differences`` the
decoder outputs a *normalized difference* :math:`\delta_t` and (Eq. acrkn-diff)

.. math:: \hat o_{t+1} = m_t + \mathrm{shift} + \mathrm{scale}\odot\delta_t,\qquad
          m_t = \begin{cases} o_t & \text{if } o_t \text{ is observed (mask True)}\\
                              \hat o_t & \text{otherwise (last prediction as memory)}\end{cases}

with :math:`m_0 = 0` when :math:`o_0` is missing. ``shift`` and ``scale`` express the
difference statistics in the units of the observations the model receives; for observations
normalized with the training statistics, :func:`difference_scaling` gives
``shift = diff_mean / obs_std`` and ``scale = diff_std / obs_std``. The memory is treated as
known: the predictive variance is ``scale² · var(δ_t)``; it grows over missing steps because the
latent prior's variance grows, which the decoder sees.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import torch
from torch import Tensor, nn

from ._checks import (check_finite, check_input_dtype, check_last_dims, check_mask, check_same_dtype, check_tensor,
                      module_dtype)
from .beliefs import DiagGaussian, FactorizedBelief
from .factorized import factorized_predict_from_matrix
from .filtering import FilterResult
from .rkn import RKN, BandParameters, Cause, LocallyLinearTransition, mlp

__all__ = [
    "check_sequences",
    "LinearControl",
    "LocallyLinearControl",
    "MLPControl",
    "ZeroControl",
    "control_cause",
    "NormBoundedTransition",
    "difference_scaling",
    "DifferenceReadout",
    "HybridReadout",
    "AcRKN",
    "InverseDynamicsHead",
    "inverse_dynamics",
    "inverse_dynamics_loss",
]

class _Control(nn.Module):
    """Common input checks of the control models. ``reads_state``: whether :math:`b` depends on
    the posterior mean (then it is a state-dependent cause, evaluated inside the filter loop)."""

    reads_state: bool = False

    def __init__(self, action_dim: int, latent_obs_dim: int) -> None:
        super().__init__()
        if action_dim <= 0 or latent_obs_dim <= 0:
            raise ValueError(f"action_dim: need action_dim > 0 and latent_obs_dim > 0, got {action_dim}, {latent_obs_dim}")
        self.action_dim, self.latent_obs_dim = action_dim, latent_obs_dim

    def _check(self, action: Tensor, mean: Tensor) -> None:
        check_last_dims("action", action, (self.action_dim,))
        check_last_dims("mean", mean, (2 * self.latent_obs_dim,))


class LinearControl(_Control):
    r"""Linear control model :math:`b(a) = B a` with :math:`B\in\mathbb R^{2m\times d_a}`, Eq. (acrkn-control-linear)."""

    def __init__(self, action_dim: int, latent_obs_dim: int, init_std: float = 0.1) -> None:
        super().__init__(action_dim, latent_obs_dim)
        self.B = nn.Parameter(init_std * torch.randn(2 * latent_obs_dim, action_dim))

    def forward(self, action: Tensor, mean: Tensor) -> Tensor:
        """``action: (..., da)``, ``mean: (..., 2m)`` (unused) -> ``(..., 2m)``."""
        self._check(action, mean)
        return action @ self.B.T


class LocallyLinearControl(_Control):
    r"""Locally linear control :math:`b(a, z) = \sum_{k=1}^K \beta_k(z)\,B^{(k)} a` with
    :math:`\beta(z) = \mathrm{softmax}(Wz + c)`, Eq. (acrkn-control-local). ``mean`` is the
    posterior mean :math:`z_t^+` (so :math:`b` stays a known quantity at predict time)."""

    reads_state = True

    def __init__(self, action_dim: int, latent_obs_dim: int, num_basis: int = 15, init_std: float = 0.1) -> None:
        super().__init__(action_dim, latent_obs_dim)
        if num_basis <= 0:
            raise ValueError(f"num_basis: must be positive, got {num_basis}")
        self.num_basis = num_basis
        self.basis = nn.Parameter(init_std * torch.randn(num_basis, 2 * latent_obs_dim, action_dim))
        self.coefficient_net = nn.Linear(2 * latent_obs_dim, num_basis)

    def coefficients(self, mean: Tensor) -> Tensor:
        """:math:`\\beta(z)`: ``(..., K)``, non-negative, summing to one."""
        return torch.softmax(self.coefficient_net(mean), dim=-1)

    def forward(self, action: Tensor, mean: Tensor) -> Tensor:
        """``action: (..., da)``, ``mean: (..., 2m)`` -> ``(..., 2m)``."""
        self._check(action, mean)
        per_basis = torch.einsum("kij,...j->...ki", self.basis, action)  # (..., K, 2m)
        return (self.coefficients(mean).unsqueeze(-1) * per_basis).sum(-2)


class MLPControl(_Control):
    r"""Nonlinear control :math:`b(a) = f(a)`, an MLP with ReLU units, Eq. (acrkn-control-mlp).

    The covariance never sees :math:`b`, so nothing forces it to be linear (the thesis' default).
    """

    def __init__(self, action_dim: int, latent_obs_dim: int, hidden: Sequence[int] = (120, 120, 120)) -> None:
        super().__init__(action_dim, latent_obs_dim)
        self.net = mlp(action_dim, hidden, 2 * latent_obs_dim)

    def forward(self, action: Tensor, mean: Tensor) -> Tensor:
        """``action: (..., da)``, ``mean: (..., 2m)`` (unused) -> ``(..., 2m)``."""
        self._check(action, mean)
        return self.net(action)


class ZeroControl(_Control):
    """:math:`b = 0`: the ac-RKN with this control model is exactly the RKN (used in tests)."""

    def forward(self, action: Tensor, mean: Tensor) -> Tensor:
        self._check(action, mean)
        return torch.zeros_like(mean)


@dataclass(frozen=True)
class _StateControl:
    """The control cause of a model whose :math:`b(a_t, z_t^+)` reads the posterior (a state cause)."""

    control: nn.Module
    actions: Tensor

    def __call__(self, t: int, posterior: FactorizedBelief) -> FactorizedBelief:
        return FactorizedBelief.known(self.control(self.actions[:, t], posterior.mean))


def control_cause(control: nn.Module, actions: Tensor) -> Cause:
    r"""The action term of Eq. (acrkn-predict) as a cause of the predict step: the known input
    :math:`b(a_t)` with zero variance. A control model that does not read the state
    (``reads_state`` False) is evaluated for the whole sequence ``actions: (B, T, da)`` at once
    (a :class:`FactorizedBelief` ``(B, T, 2m)``); :class:`LocallyLinearControl` becomes a state
    cause evaluated inside the loop on :math:`z_t^+`."""
    if getattr(control, "reads_state", True):
        return _StateControl(control, actions)
    zeros = actions.new_zeros(*actions.shape[:-1], 2 * control.latent_obs_dim)
    return FactorizedBelief.known(control(actions, zeros))


class NormBoundedTransition(nn.Module):
    r"""A locally linear transition whose every :math:`A_t` has spectral norm at most ``max_norm``.

    *Our addition, not in the thesis.* Open-loop prediction runs the predict step many times with
    no update. If some :math:`\|A_t\|_2 > 1` the latent mean can grow without bound (we see this
    happen in Chapter 4). :math:`A_t = \sum_k \alpha_k(z) M_k` with :math:`M_k = I + A^{(k)}` is a
    convex combination (the :math:`\alpha_k` are softmax weights), so
    :math:`\|A_t\|_2 \le \max_k \|M_k\|_2`. We rescale each basis matrix once per sequence,
    Eq. (acrkn-norm-bound):

    .. math:: \tilde M_k = M_k \,/\, \max\big(1, \|M_k\|_2 / \rho\big)
              \quad\Rightarrow\quad \|A_t\|_2 \le \rho \text{ for every } t \text{ and every } z,

    which makes the mean dynamics without inputs non-expansive for ``max_norm`` :math:`\rho\le 1`
    — for time-varying :math:`A_t` too, where eigenvalues inside the unit circle would not be enough.
    Wraps (and shares the parameters of) a :class:`pgm_wm.rkn.LocallyLinearTransition`; the band
    structure and the factorized predict (Eq. rkn-predict) are unchanged.
    """

    def __init__(self, base: LocallyLinearTransition, max_norm: float = 1.0) -> None:
        super().__init__()
        if max_norm <= 0:
            raise ValueError(f"max_norm: must be positive, got {max_norm}")
        self.base, self.max_norm = base, float(max_norm)
        self.latent_obs_dim = base.latent_obs_dim

    @property
    def trans_var(self) -> Tensor:
        return self.base.trans_var

    @property
    def constant(self) -> bool:
        return self.base.constant

    @property
    def diagonal_blocks(self) -> bool:
        return self.base.diagonal_blocks

    def scaled_basis(self) -> Tensor:
        """:math:`\tilde M_k`: ``(K, 2m, 2m)`` with spectral norms ``<= max_norm``."""
        M = self.base.dense_basis()
        if self.base.add_identity:
            M = M + torch.eye(M.shape[-1], dtype=M.dtype, device=M.device)
        norms = torch.linalg.matrix_norm(M, ord=2)
        return M / torch.clamp(norms / self.max_norm, min=1.0)[:, None, None]

    def band_parameters(self) -> BandParameters:
        r"""The bounded transition in the band storage of the compiled filter: the rescaled
        :math:`\tilde M_k` (identity included) at the band pairs, nothing added."""
        base = self.base.band_parameters()
        M, m = self.scaled_basis(), self.latent_obs_dim
        ii, jj = torch.as_tensor(base.bi), torch.as_tensor(base.bj)
        basis = torch.stack([M[:, ii, jj], M[:, ii, m + jj], M[:, m + ii, jj], M[:, m + ii, m + jj]])
        return BandParameters(basis, torch.zeros_like(base.ident), base.bi, base.bj, base.weight, base.bias)

    def dense_matrix(self, mean: Tensor) -> Tensor:
        r""":math:`A_t = \sum_k \alpha_k(z)\tilde M_k`: ``(..., 2m, 2m)``."""
        check_last_dims("mean", mean, (2 * self.latent_obs_dim,))
        return self._mix(mean, self.scaled_basis())

    def _mix(self, mean: Tensor, basis: Tensor) -> Tensor:
        if basis.shape[0] == 1:
            return basis[0]
        alpha = self.base.coefficients(mean)
        n = basis.shape[-1]
        return (alpha @ basis.reshape(basis.shape[0], n * n)).reshape(*alpha.shape[:-1], n, n)

    def predictor(self) -> Callable[..., FactorizedBelief]:
        """Predict function ``(post, causes=()) -> prior`` with the basis rescaled once."""
        basis, q = self.scaled_basis(), self.base.trans_var

        def predict(post: FactorizedBelief, causes: Sequence[FactorizedBelief] = ()) -> FactorizedBelief:
            return factorized_predict_from_matrix(post, self._mix(post.mean, basis), q, causes, validate=False)

        return predict

    def forward(self, post: FactorizedBelief, causes: Sequence[FactorizedBelief] = ()) -> FactorizedBelief:
        """Predict step, Eq. (rkn-predict) with the bounded :math:`A_t`."""
        return self.predictor()(post, causes)


def difference_scaling(stats: Mapping[str, Any]) -> tuple[Tensor, Tensor]:
    """``(shift, scale)`` of :class:`DifferenceReadout` for observations normalized with ``stats``.

    Differences :math:`o_{t+1}-o_t` in original units are standardized with ``diff_mean`` and
    ``diff_std``; observations with ``obs_mean`` and ``obs_std``. A standardized difference
    :math:`\\delta` is, in normalized-observation units, ``diff_mean/obs_std + (diff_std/obs_std) δ``.
    """
    for key in ("obs_std", "diff_mean", "diff_std"):
        if key not in stats:
            raise ValueError(f"stats: missing key {key!r}")
    obs_std = torch.as_tensor(stats["obs_std"], dtype=torch.get_default_dtype())
    shift = torch.as_tensor(stats["diff_mean"], dtype=obs_std.dtype) / obs_std
    scale = torch.as_tensor(stats["diff_std"], dtype=obs_std.dtype) / obs_std
    if not bool((scale > 0).all()):
        raise ValueError("stats: diff_std / obs_std must be positive")
    return shift, scale


class DifferenceReadout(nn.Module):
    r"""Turn decoded normalized differences into next-observation predictions, Eq. (acrkn-diff).

    ``predict_differences=False``: the decoder output *is* the prediction of :math:`o_{t+1}`
    (``memory`` is then unused).
    ``predict_differences=True``: :math:`\hat o_{t+1} = m_t + \mathrm{shift} + \mathrm{scale}\odot\delta_t`
    with the memory :math:`m_t` = the observation if observed, else the previous prediction.
    Shared by :class:`AcRKN` and the recurrent baselines (:mod:`pgm_wm.baselines`).
    """

    def __init__(self, obs_dim: int, predict_differences: bool = True,
                 shift: Tensor | Sequence[float] | None = None,
                 scale: Tensor | Sequence[float] | None = None,
                 var_floor: float = 1e-4) -> None:
        super().__init__()
        if var_floor < 0:
            raise ValueError(f"var_floor: must be >= 0, got {var_floor}")
        self.obs_dim, self.predict_differences, self.var_floor = obs_dim, predict_differences, float(var_floor)
        shift_t = torch.zeros(obs_dim) if shift is None else torch.as_tensor(shift, dtype=torch.get_default_dtype()).clone()
        scale_t = torch.ones(obs_dim) if scale is None else torch.as_tensor(scale, dtype=torch.get_default_dtype()).clone()
        if shift_t.shape != (obs_dim,):
            raise ValueError(f"shift: expected shape ({obs_dim},), got {tuple(shift_t.shape)}")
        if scale_t.shape != (obs_dim,) or not bool((scale_t > 0).all()):
            raise ValueError(f"scale: expected a positive vector of shape ({obs_dim},)")
        self.register_buffer("shift", shift_t)
        self.register_buffer("scale", scale_t)

    @property
    def decoder_dim(self) -> int:
        """How many entries the decoder must emit per step (``obs_dim`` here)."""
        return self.obs_dim

    def step(self, memory: Tensor, delta_mean: Tensor, delta_var: Tensor) -> tuple[Tensor, Tensor]:
        """One step: ``memory, delta_mean, delta_var: (..., do)`` -> prediction ``(mean, var)``.

        ``var_floor`` is added to the decoded variance (in decoder units) so that an ``elu + 1``
        output that underflows to 0 in float32 cannot make the likelihood infinite."""
        return self.step_mean(memory, delta_mean), self.step_var(delta_var)

    def step_mean(self, memory: Tensor, delta_mean: Tensor) -> Tensor:
        """The mean of :meth:`step`: ``memory + shift + scale * delta_mean`` (or ``delta_mean``)."""
        if not self.predict_differences:
            return delta_mean
        return memory + self.shift.to(delta_mean.dtype) + self.scale.to(delta_mean.dtype) * delta_mean

    def step_var(self, delta_var: Tensor) -> Tensor:
        """The variance of :meth:`step`: ``scale² (delta_var + var_floor)`` (it never depends on
        the memory, so a caller may compute it for all steps at once)."""
        delta_var = delta_var + self.var_floor
        if not self.predict_differences:
            return delta_var
        scale = self.scale.to(delta_var.dtype)
        return scale * scale * delta_var

    @staticmethod
    def memory(obs_t: Tensor, mask_t: Tensor | None, last_pred: Tensor | None) -> Tensor:
        """:math:`m_t`: ``obs_t`` where ``mask_t`` else ``last_pred`` (zeros if there is none)."""
        if mask_t is None:
            return obs_t
        prev = torch.zeros_like(obs_t) if last_pred is None else last_pred
        return torch.where(mask_t[..., None], obs_t, prev)

    def forward(self, obs: Tensor, mask: Tensor | None, delta_mean: Tensor, delta_var: Tensor,
                last: Tensor | None = None) -> tuple[Tensor, Tensor]:
        r"""Whole sequence: ``obs, delta_mean, delta_var: (B, T, do)``, ``mask: (B, T)`` -> ``(mean, var)``.

        ``last: (B, do)`` is the prediction of ``obs[:, 0]`` made before this sequence (the memory
        if that step is masked; default zeros), e.g. carried from the previous window.

        Unrolled, Eq. (acrkn-diff) says: with :math:`j \le t` the last observed step,
        :math:`\hat o_{t+1} = o_j + \sum_{s=j}^{t} c_s` with :math:`c_s = \mathrm{shift} +
        \mathrm{scale}\odot\delta_s` (and :math:`\hat o_{t+1} = 	ext{last} + \sum_{s\le t} c_s`
        before the first observation). So the whole sequence is one running sum
        :math:`C_t = \sum_{s\le t} c_s` (accumulated in float64) and a gather of :math:`o_j` and
        :math:`C_{j-1}`: :math:`\hat o_{t+1} = o_j + C_t - C_{j-1}`, a handful of tensor operations
        instead of a loop over time. Tested equal to :meth:`loop`, the step-by-step reference."""
        if not self.predict_differences or mask is None:
            return self.step(obs, delta_mean, delta_var)
        B, T, do = obs.shape
        shift, scale = self.shift.to(delta_mean.dtype), self.scale.to(delta_mean.dtype)
        steps = (shift + scale * delta_mean).double()
        C = torch.cat([steps.new_zeros(B, 1, do), steps.cumsum(1)], 1)              # C[:, t + 1] = C_t
        seen = torch.where(mask, torch.arange(T, device=obs.device), -1).cummax(1).values   # j(t), -1: none yet
        j = seen.clamp_min(0)[..., None].expand(B, T, do)
        start = torch.zeros_like(obs[:, 0]) if last is None else last
        base = torch.where((seen >= 0)[..., None], obs.gather(1, j), start[:, None, :])
        mean = base + (C[:, 1:] - C.gather(1, j)).to(obs.dtype)
        return mean, scale * scale * (delta_var + self.var_floor)

    def loop(self, obs: Tensor, mask: Tensor | None, delta_mean: Tensor, delta_var: Tensor,
             last: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """:meth:`forward` written as the recursion of Eq. (acrkn-diff), one :meth:`step` per time
        step with the memory rule :meth:`memory` (the readable reference)."""
        if mask is None:
            return self.step(obs, delta_mean, delta_var)
        means, vars_ = [], []
        for t in range(obs.shape[1]):
            mem = self.memory(obs[:, t], mask[:, t], last)
            mu, var = self.step(mem, delta_mean[:, t], delta_var[:, t])
            means.append(mu)
            vars_.append(var)
            last = mu
        return torch.stack(means, 1), torch.stack(vars_, 1)


class HybridReadout(DifferenceReadout):
    r"""A gated mix of the difference and the absolute readout, Eq. (acrkn-hybrid):

    .. math::
        \hat o_{t+1} = g \odot \big(m_t + \mathrm{shift} + \mathrm{scale}\odot\delta_t\big)
        + (1 - g) \odot a_t, \qquad g = \operatorname{sigmoid}(\gamma),

    where the decoder emits both a normalized difference :math:`\delta_t` and an absolute
    prediction :math:`a_t` (so its output has ``2 * obs_dim`` entries, :attr:`decoder_dim`) and
    :math:`\gamma` is one learned logit per observation dimension (initialised at 0, an even
    mix). Treating the two decoded parts as independent Gaussians, the variance is
    :math:`g^2\,\mathrm{scale}^2\,\mathrm{var}_\delta + (1-g)^2\,\mathrm{var}_a`.
    :math:`g \to 1` recovers the difference readout, :math:`g \to 0` the absolute one; in open
    loop the absolute part ties the running sum :math:`m_t` to what the latent state decodes.
    """

    def __init__(self, obs_dim: int, shift: Tensor | Sequence[float] | None = None,
                 scale: Tensor | Sequence[float] | None = None, var_floor: float = 1e-4) -> None:
        super().__init__(obs_dim, True, shift, scale, var_floor)
        self.gate_logit = nn.Parameter(torch.zeros(obs_dim))

    @property
    def decoder_dim(self) -> int:
        return 2 * self.obs_dim

    def step(self, memory: Tensor, delta_mean: Tensor, delta_var: Tensor) -> tuple[Tensor, Tensor]:
        """One step: ``memory: (..., do)``, ``delta_mean, delta_var: (..., 2 do)`` (difference
        part first, absolute part second) -> prediction ``(mean, var)`` each ``(..., do)``."""
        check_last_dims("delta_mean", delta_mean, (self.decoder_dim,))
        check_last_dims("delta_var", delta_var, (self.decoder_dim,))
        do = self.obs_dim
        diff_mean, diff_var = super().step(memory, delta_mean[..., :do], delta_var[..., :do])
        abs_mean, abs_var = delta_mean[..., do:], delta_var[..., do:] + self.var_floor
        g = torch.sigmoid(self.gate_logit.to(delta_mean.dtype))
        return g * diff_mean + (1 - g) * abs_mean, g * g * diff_var + (1 - g) * (1 - g) * abs_var

    def forward(self, obs: Tensor, mask: Tensor | None, delta_mean: Tensor, delta_var: Tensor,
                last: Tensor | None = None) -> tuple[Tensor, Tensor]:
        r"""Whole sequence: ``obs: (B, T, do)``, ``delta_mean, delta_var: (B, T, 2 do)``, ``mask:
        (B, T)`` -> ``(mean, var)`` each ``(B, T, do)``; ``last`` as in :meth:`DifferenceReadout.forward`.

        With the memory rule, Eq. (acrkn-hybrid) is a first-order linear recursion in the mean,
        :math:`\hat o_{t+1} = \alpha_t \hat o_t + \beta_t` with :math:`\alpha_t = g\,(1 - \text{mask}_t)`
        and :math:`\beta_t = g \odot (\text{mask}_t\, o_t + \mathrm{shift} + \mathrm{scale}\odot\delta_t)
        + (1-g)\odot a_t` (:math:`\hat o_0` = ``last``). Pairs :math:`(\alpha, \beta)` compose
        associatively, :math:`(\alpha_2, \beta_2)\circ(\alpha_1, \beta_1) = (\alpha_2\alpha_1,
        \alpha_2\beta_1 + \beta_2)`, so the whole sequence is an inclusive scan of
        :math:`\lceil\log_2 T\rceil` tensor steps instead of a loop over time (products of
        :math:`g \in (0, 1)` only shrink: nothing overflows). Tested equal to :meth:`loop`, the
        step-by-step reference."""
        if mask is None:
            return self.step(obs, delta_mean, delta_var)
        check_last_dims("delta_mean", delta_mean, (self.decoder_dim,))
        check_last_dims("delta_var", delta_var, (self.decoder_dim,))
        do, T = self.obs_dim, obs.shape[1]
        dtype = delta_mean.dtype
        g = torch.sigmoid(self.gate_logit.to(dtype))
        seen = mask[..., None].to(dtype)
        observed = torch.where(mask[..., None], obs, torch.zeros((), dtype=obs.dtype, device=obs.device))
        step = self.shift.to(dtype) + self.scale.to(dtype) * delta_mean[..., :do]
        alpha = (g * (1 - seen)).expand(-1, -1, do)
        beta = g * (observed + step) + (1 - g) * delta_mean[..., do:]
        shift = 1
        while shift < T:                       # Hillis-Steele: after it, mean_t = alpha_t * last + beta_t
            alpha_prev = torch.cat([alpha.new_ones(alpha.shape[0], shift, do), alpha[:, :-shift]], 1)
            beta_prev = torch.cat([beta.new_zeros(beta.shape[0], shift, do), beta[:, :-shift]], 1)
            alpha, beta = alpha * alpha_prev, alpha * beta_prev + beta
            shift *= 2
        mean = beta if last is None else alpha * last[:, None, :] + beta
        diff_var = super().step_var(delta_var[..., :do])
        var = g * g * diff_var + (1 - g) * (1 - g) * (delta_var[..., do:] + self.var_floor)
        return mean, var


def check_sequences(obs: Tensor, actions: Tensor | None, mask: Tensor | None,
                     obs_dim: int | None = None, action_dim: int | None = None,
                     model: object | None = None) -> Tensor | None:
    """Check ``obs: (B, T, do)``, ``actions: (B, T, da)``, ``mask: (B, T)``; return the bool mask.

    One dtype rule: ``obs`` and ``actions`` float32 or float64, of one dtype, and (when ``model``
    is given) the dtype of the model's parameters. Observations must be finite where observed."""
    check_tensor("obs", obs, 3)
    B, T = obs.shape[:2]
    if T == 0:
        raise ValueError("obs: need at least one time step, got T = 0")
    check_same_dtype(("obs", "actions"), (obs, actions))
    if model is not None:
        check_input_dtype("obs", obs, module_dtype(model))
    if obs_dim is not None:
        check_last_dims("obs", obs, (obs_dim,))
    if actions is not None:
        check_tensor("actions", actions, 3)
        if tuple(actions.shape[:2]) != (B, T):
            raise ValueError(f"actions: expected leading shape {(B, T)}, got {tuple(actions.shape)}")
        if action_dim is not None:
            check_last_dims("actions", actions, (action_dim,))
        check_finite("actions", actions)
    if mask is not None:
        mask = check_mask("mask", mask, (B, T))
    check_finite("obs", obs.detach() if mask is None else obs.detach()[mask])
    return mask


class AcRKN(nn.Module):
    """Action-conditional RKN: ``encoder -> [update, predict + b(a)]* -> decoder`` (Chapter 4).

    Composes an :class:`pgm_wm.rkn.RKN` (attribute ``rkn``) and a control model; the control
    term enters the RKN's predict step as one more cause (:meth:`causes`).

    Args:
        encoder: ``obs (..., do) -> (w, w_var) (..., m)``, e.g. :class:`pgm_wm.rkn.ObservationEncoder`.
        transition: :class:`pgm_wm.rkn.LocallyLinearTransition` or :class:`NormBoundedTransition`.
        control: one of the control models of this module.
        decoder: ``FactorizedBelief -> (mean, var) (..., do)``, e.g. :class:`pgm_wm.rkn.BeliefDecoder`.
        init_var: initial belief variance.
        predict_differences, diff_shift, diff_scale: see :class:`DifferenceReadout`.
        readout: a readout module instead (e.g. :class:`HybridReadout`); the decoder's
            ``out_dim`` must then equal its ``decoder_dim``, and the three arguments above are unused.
    """

    def __init__(
        self,
        encoder: nn.Module,
        transition: nn.Module,
        control: nn.Module,
        decoder: nn.Module,
        init_var: float = 10.0,
        predict_differences: bool = True,
        diff_shift: Tensor | Sequence[float] | None = None,
        diff_scale: Tensor | Sequence[float] | None = None,
        readout: DifferenceReadout | None = None,
    ) -> None:
        super().__init__()
        self.rkn = RKN(encoder, transition, decoder, init_var)
        self.control = control
        out_dim = getattr(decoder, "out_dim", None)
        if out_dim is None:
            raise ValueError("decoder: needs an `out_dim` attribute (the observation size)")
        if readout is None:
            readout = DifferenceReadout(out_dim, predict_differences, diff_shift, diff_scale)
        elif not isinstance(readout, DifferenceReadout):
            raise ValueError(f"readout: expected a DifferenceReadout, got {type(readout).__name__}")
        if readout.decoder_dim != out_dim:
            raise ValueError(f"decoder: out_dim {out_dim} differs from the readout's decoder_dim {readout.decoder_dim}")
        self.obs_dim = readout.obs_dim
        self.action_dim = getattr(control, "action_dim", None)
        self.latent_obs_dim = transition.latent_obs_dim
        if getattr(control, "latent_obs_dim", self.latent_obs_dim) != self.latent_obs_dim:
            raise ValueError("control: latent_obs_dim differs from the transition's")
        self.readout = readout

    @property
    def encoder(self) -> nn.Module:
        return self.rkn.encoder

    @property
    def transition(self) -> nn.Module:
        return self.rkn.transition

    @property
    def decoder(self) -> nn.Module:
        return self.rkn.decoder

    @property
    def predict_differences(self) -> bool:
        return self.readout.predict_differences

    def causes(self, actions: Tensor | None) -> list[Cause]:
        """The causes this model adds to the RKN's predict step: ``[control cause]``
        (:func:`control_cause`; none for ``actions=None``). ac-RKN = RKN + this list."""
        return [] if actions is None else [control_cause(self.control, actions)]

    def initial_belief(self, batch_shape: Sequence[int], like: Tensor) -> FactorizedBelief:
        """The belief of the first step, ``N(0, init_var · I)`` (:meth:`pgm_wm.rkn.RKN.initial_belief`)."""
        return self.rkn.initial_belief(batch_shape, like)

    def encode(self, obs: Tensor, mask: Tensor | None = None, *, validate: bool = True) -> DiagGaussian:
        """Eq. (rkn-encoder) on ``obs: (B, T, do)`` with the masked steps zeroed first
        (:meth:`pgm_wm.rkn.RKN.encode`)."""
        return self.rkn.encode(obs, mask, validate=validate)

    def filter(
        self,
        obs: Tensor,
        actions: Tensor | None,
        mask: Tensor | None = None,
        causes: Sequence[Cause] = (),
        init: FactorizedBelief | None = None,
        *,
        validate: bool = True,
    ) -> FilterResult[FactorizedBelief]:
        r"""The world model's one filter path: encode ``obs: (B, T, do)``, then
        ``[update, predict]*`` with the causes :meth:`causes` ``(actions)`` plus ``causes``.

        ``actions: (B, T, da)``: ``actions[:, t]`` acts in the predict step ``t -> t+1``. ``None``
        drops the control term (the plain RKN; used for the no-feedback inverse-dynamics ablation).
        ``mask: (B, T)`` True = observed; observations at masked steps are zeroed before
        encoding, so their values can never reach the beliefs or the gradients.
        ``causes`` are further independent causes of the same predict step, appended after the
        control term: the HiP-RSSM adds its latent task here (Chapter 5), MTS3 the slow level's
        task (Chapter 6). ``init``: the belief of the first step (default :meth:`initial_belief`).
        ``validate=False`` skips the input checks, for callers that checked their inputs once
        (:meth:`forward` does, the later chapters' models do at their own boundary).
        """
        if validate:        # the encoder checks the observation size (a filter needs no readout)
            mask = check_sequences(obs, actions, mask, None, self.action_dim, model=self)
        w = self.rkn.encode(obs, mask, validate=False)
        return self.latent_filter(w, mask, self.causes(actions) + list(causes), init)

    def latent_filter(self, observation: DiagGaussian, mask: Tensor | None, causes: Sequence[Cause],
                      init: FactorizedBelief | None = None) -> FilterResult[FactorizedBelief]:
        """:meth:`filter` after the encoder: ``[update, predict]*`` over encoded observations
        ``DiagGaussian(w, w_var)`` (:meth:`encode`) with the *complete* list of causes (this
        model's :meth:`causes` first). For a caller that encodes and builds the causes once and
        filters pieces of them (MTS3's windows); no input checks."""
        return self.rkn.filter(observation, mask=mask, causes=causes, init=init, validate=False)

    @property
    def causes_known_in_advance(self) -> bool:
        """True if every cause of :meth:`causes` is known before the loop (the control model
        does not read the state), so a caller may slice the causes of a sequence into pieces."""
        return not getattr(self.control, "reads_state", True)

    def decode_predictions(self, out: FilterResult, obs: Tensor, mask: Tensor | None,
                           last: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Decode ``out.next_prior`` and apply Eq. (acrkn-diff): ``(mean, var)`` each ``(B, T, do)``.
        ``last``: the readout's memory carried from before ``obs[:, 0]`` (:meth:`DifferenceReadout.forward`)."""
        d_mean, d_var = self.rkn.decoder(out.next_prior)
        return self.readout(obs, mask, d_mean, d_var, last=last)

    def forward(
        self,
        obs: Tensor,
        actions: Tensor,
        mask: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Predict :math:`o_{t+1}` for every ``t``: ``(mean, var)`` each ``(B, T, do)``.

        Uses only observations with ``mask`` True at indices ``<= t`` and actions ``<= t``.
        The inputs are checked once here; nothing inside the time loop synchronises with the host.
        """
        mask = check_sequences(obs, actions, mask, self.obs_dim, self.action_dim, model=self)
        out = self.filter(obs, actions, mask, validate=False)
        return self.decode_predictions(out, obs, mask)


class InverseDynamicsHead(nn.Module):
    r"""Action decoder for inverse dynamics (thesis appendix A), Eq. (acrkn-inverse):

    .. math:: \hat a_t = g\big([z_t^+;\; w_{t+1}]\big),

    from the posterior mean :math:`z_t^+` (which has seen :math:`o_{\le t}`, :math:`a_{<t}`) and the
    encoded desired next observation :math:`w_{t+1} = \mathrm{enc}(o_{t+1})`.
    """

    def __init__(self, latent_obs_dim: int, action_dim: int, hidden: Sequence[int] = (64,)) -> None:
        super().__init__()
        self.latent_obs_dim, self.action_dim = latent_obs_dim, action_dim
        self.net = mlp(3 * latent_obs_dim, hidden, action_dim)

    def forward(self, post_mean: Tensor, next_w: Tensor) -> Tensor:
        """``post_mean: (..., 2m)``, ``next_w: (..., m)`` -> ``(..., da)``."""
        check_last_dims("post_mean", post_mean, (2 * self.latent_obs_dim,))
        check_last_dims("next_w", next_w, (self.latent_obs_dim,))
        return self.net(torch.cat([post_mean, next_w], dim=-1))


def inverse_dynamics(
    model: AcRKN, head: InverseDynamicsHead, obs: Tensor, actions: Tensor, action_feedback: bool = True,
) -> tuple[Tensor, Tensor, Tensor]:
    """Joint inverse/forward pass over fully observed ``obs: (B, T, do)``, ``actions: (B, T, da)``.

    Returns ``(action_pred (B, T-1, da), fwd_mean (B, T, do), fwd_var (B, T, do))``: ``action_pred[:, t]``
    estimates :math:`a_t` from :math:`z_t^+` and :math:`o_{t+1}`; the forward outputs predict
    :math:`o_{t+1}` as in :meth:`AcRKN.forward`. With ``action_feedback`` the executed action is fed
    to the predict step *after* it was decoded (so :math:`\\hat a_t` never sees :math:`a_t`);
    without it the filter has no control term.
    """
    check_sequences(obs, actions, None, model.obs_dim)
    if obs.shape[1] < 2:
        raise ValueError(f"obs: need at least 2 time steps, got {obs.shape[1]}")
    out = model.filter(obs, actions if action_feedback else None, None)
    w_next, _ = model.encoder(obs[:, 1:])
    a_hat = head(out.posterior.mean[:, :-1], w_next)
    fwd_mean, fwd_var = model.decode_predictions(out, obs, None)
    return a_hat, fwd_mean, fwd_var


def inverse_dynamics_loss(
    model: AcRKN, head: InverseDynamicsHead, obs: Tensor, actions: Tensor,
    lam: float = 0.1, action_feedback: bool = True,
) -> Tensor:
    r"""Eq. (acrkn-inverse-loss): :math:`\mathrm{MSE}(\hat a_t, a_t) + \lambda\,\mathrm{MSE}(\hat o_{t+1}, o_{t+1})`,
    averaged over :math:`t = 0..T-2` and all dimensions (units of the inputs, e.g. normalized)."""
    if lam < 0:
        raise ValueError(f"lam: must be non-negative, got {lam}")
    a_hat, f_mean, _ = inverse_dynamics(model, head, obs, actions, action_feedback)
    inv = ((a_hat - actions[:, :-1]) ** 2).mean()
    fwd = ((f_mean[:, :-1] - obs[:, 1:]) ** 2).mean()
    return inv + lam * fwd
