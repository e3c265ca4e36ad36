r"""Probes: how much of a known quantity a learned representation carries (Chapters 5 and 6).

A probe is a small regression from a representation :math:`X` (e.g. the HiP-RSSM's task means
:math:`\mu_l` of many windows) to a quantity :math:`Y` the model was never told (the payload),
fitted on one set of windows and scored on another, held-out one. Its score is the coefficient of
determination, Eq. (probe-r2),

.. math:: R^2 = 1 - \frac{\sum_{n,j} (Y_{nj} - \hat Y_{nj})^2}{\sum_{n,j} (Y_{nj} - \bar Y_j)^2},

the share of the held-out variance of :math:`Y` that the probe's prediction :math:`\hat Y`
explains (:math:`\bar Y` the held-out mean; it can be negative for a probe worse than the mean).

* :func:`linear_probe_r2`: least squares on :math:`[X, 1]` (what a linear read-out finds);
* :func:`mlp_probe_r2`: a one-hidden-layer network, trained full-batch with Adam and early
  stopping on a held-out fifth of the fitting set (a small nonlinear read-out: it finds what a
  curved map of :math:`X` carries, which a linear probe can miss).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ._checks import check_tensor

__all__ = ["r2_score", "linear_probe_r2", "mlp_probe_r2"]


def _as_2d(name: str, x: Tensor) -> Tensor:
    check_tensor(name, x, 1)
    x = x.double()
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2:
        raise ValueError(f"{name}: expected (n,) or (n, d), got {tuple(x.shape)}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name}: contains NaN or infinite values")
    return x


def _pairs(X_fit: Tensor, Y_fit: Tensor, X: Tensor, Y: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    X_fit, Y_fit, X, Y = (_as_2d(n, v) for n, v in (("X_fit", X_fit), ("Y_fit", Y_fit), ("X", X), ("Y", Y)))
    if X_fit.shape[0] != Y_fit.shape[0] or X.shape[0] != Y.shape[0]:
        raise ValueError(f"Y_fit: X and Y need the same number of rows, got {X_fit.shape[0]}/{Y_fit.shape[0]} and "
                         f"{X.shape[0]}/{Y.shape[0]}")
    if X_fit.shape[1] != X.shape[1] or Y_fit.shape[1] != Y.shape[1]:
        raise ValueError("X: the fitting and the held-out sets need the same columns")
    if X_fit.shape[0] < 2 or X.shape[0] < 2:
        raise ValueError("X_fit: need at least two rows in each set")
    return X_fit, Y_fit, X, Y


def r2_score(pred: Tensor, target: Tensor) -> float:
    """Eq. (probe-r2): ``1 - SSE / SST`` over all rows and columns (``SST`` around the column means
    of ``target``)."""
    pred, target = _as_2d("pred", pred), _as_2d("target", target)
    if pred.shape != target.shape:
        raise ValueError(f"pred: expected the shape of target {tuple(target.shape)}, got {tuple(pred.shape)}")
    sst = float((target - target.mean(0)).square().sum())
    if sst <= 0:
        raise ValueError("target: has no variance, R² is undefined")
    return 1.0 - float((target - pred).square().sum()) / sst


def linear_probe_r2(X_fit: Tensor, Y_fit: Tensor, X: Tensor, Y: Tensor) -> float:
    """Least squares ``Y ~ [X, 1]`` fitted on ``(X_fit, Y_fit)``; :func:`r2_score` on ``(X, Y)``."""
    X_fit, Y_fit, X, Y = _pairs(X_fit, Y_fit, X, Y)
    design = lambda x: torch.cat([x, torch.ones(len(x), 1, dtype=x.dtype)], 1)  # noqa: E731
    coef = torch.linalg.lstsq(design(X_fit), Y_fit).solution
    return r2_score(design(X) @ coef, Y)


def mlp_probe_r2(X_fit: Tensor, Y_fit: Tensor, X: Tensor, Y: Tensor, hidden: int = 32, steps: int = 2000,
                 lr: float = 1e-2, seed: int = 0) -> float:
    """A one-hidden-layer ``tanh`` network fitted to ``(X_fit, Y_fit)`` (inputs and targets
    standardized with the fitting set's statistics, full-batch Adam, the parameters of the best
    loss on a held-out fifth of the fitting set kept); :func:`r2_score` on ``(X, Y)``. Seeded."""
    X_fit, Y_fit, X, Y = _pairs(X_fit, Y_fit, X, Y)
    if hidden < 1 or steps < 1 or not lr > 0:
        raise ValueError(f"hidden: need hidden >= 1, steps >= 1 and lr > 0, got {hidden}, {steps}, {lr}")
    g = torch.Generator().manual_seed(seed)
    mx, sx = X_fit.mean(0), X_fit.std(0).clamp_min(1e-12)
    my, sy = Y_fit.mean(0), Y_fit.std(0).clamp_min(1e-12)
    xs, ys = (X_fit - mx) / sx, (Y_fit - my) / sy
    perm = torch.randperm(len(xs), generator=g)
    n_hold = max(1, len(xs) // 5)
    hold, train = perm[:n_hold], perm[n_hold:]
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(xs.shape[1], hidden), nn.Tanh(), nn.Linear(hidden, ys.shape[1])).double()
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    best, best_state = float("inf"), None
    for _ in range(steps):
        opt.zero_grad()
        (net(xs[train]) - ys[train]).square().mean().backward()
        opt.step()
        with torch.no_grad():
            loss = float((net(xs[hold]) - ys[hold]).square().mean())
        if loss < best:
            best, best_state = loss, {k: v.clone() for k, v in net.state_dict().items()}
    net.load_state_dict(best_state)
    with torch.no_grad():
        return r2_score(net((X - mx) / sx) * sy + my, Y)
