"""Input validation shared by every public function of :mod:`pgm_wm`.

Every check raises :class:`ValueError` whose message starts with the name of
the offending argument, so a reader who passes a wrong shape sees at once
*which* argument was wrong and *what* was expected.

The checks are cheap (shape inspection plus one reduction) and are skipped for
tensors that require gradients only where they would force a host sync in a
hot loop; callers inside training loops may pass ``validate=False`` to the
functions that offer it.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

__all__ = [
    "NonFiniteError",
    "as_tensor",
    "check_tensor",
    "check_last_dims",
    "check_positive",
    "check_nonnegative",
    "check_finite",
    "check_spd",
    "check_mask",
    "check_same_batch",
]


class NonFiniteError(ValueError):
    """A value that must be finite is NaN or infinite. A :class:`ValueError` like every other
    check's error; its own class lets :func:`pgm_wm.training.fit` tell a diverged training run
    (a model whose outputs overflowed) from a wrong argument."""


def as_tensor(name: str, x: object, dtype: torch.dtype | None = None) -> Tensor:
    """Convert ``x`` to a floating tensor, raising ``ValueError`` naming ``name``."""
    if isinstance(x, Tensor):
        t = x
    else:
        try:
            t = torch.as_tensor(x)
        except (TypeError, ValueError, RuntimeError) as err:
            raise ValueError(f"{name}: cannot be converted to a tensor ({err})") from err
    if dtype is not None:
        t = t.to(dtype)
    if not torch.is_floating_point(t):
        t = t.to(torch.get_default_dtype())
    return t


def check_tensor(name: str, x: object, min_ndim: int = 0) -> Tensor:
    """Require a floating-point tensor with at least ``min_ndim`` dimensions."""
    if not isinstance(x, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if not torch.is_floating_point(x):
        raise ValueError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")
    if x.ndim < min_ndim:
        raise ValueError(
            f"{name}: expected at least {min_ndim} dimensions, got shape {tuple(x.shape)}"
        )
    return x


def check_last_dims(name: str, x: Tensor, dims: Sequence[int | None]) -> Tensor:
    """Require ``x.shape[-len(dims):] == dims`` (``None`` matches any size)."""
    check_tensor(name, x, min_ndim=len(dims))
    tail = tuple(x.shape[x.ndim - len(dims):]) if dims else ()
    for got, want in zip(tail, dims):
        if want is not None and got != want:
            want_str = "(..., " + ", ".join("*" if d is None else str(d) for d in dims) + ")"
            raise ValueError(
                f"{name}: expected shape {want_str}, got {tuple(x.shape)}"
            )
    return x


def check_finite(name: str, x: Tensor) -> Tensor:
    """Require all entries of ``x`` to be finite (no NaN / inf)."""
    if not bool(torch.isfinite(x).all()):
        raise NonFiniteError(f"{name}: contains NaN or infinite values")
    return x


def check_positive(name: str, x: Tensor) -> Tensor:
    """Require every entry of a variance-like tensor to be strictly positive and finite."""
    check_tensor(name, x)
    if not bool(torch.isfinite(x).all()):
        raise NonFiniteError(f"{name}: variances must be finite, got NaN or inf")
    if not bool((x > 0).all()):
        raise ValueError(
            f"{name}: variances must be strictly positive, got min {float(x.min()):.3g}"
        )
    return x


def check_nonnegative(name: str, x: Tensor) -> Tensor:
    """Require every entry of ``x`` to be >= 0 and finite."""
    check_tensor(name, x)
    if not bool(torch.isfinite(x).all()):
        raise NonFiniteError(f"{name}: must be finite, got NaN or inf")
    if not bool((x >= 0).all()):
        raise ValueError(f"{name}: must be non-negative, got min {float(x.min()):.3g}")
    return x


def check_spd(name: str, cov: Tensor, semidefinite: bool = False) -> Tensor:
    """Require a (batch of) symmetric positive-definite matrices ``(..., n, n)``.

    Symmetry is checked to a relative tolerance; definiteness by a Cholesky
    factorization (or eigenvalues >= -tol when ``semidefinite``).
    """
    check_tensor(name, cov, min_ndim=2)
    if cov.shape[-1] != cov.shape[-2]:
        raise ValueError(f"{name}: expected square matrices (..., n, n), got {tuple(cov.shape)}")
    original, cov = cov, cov.detach()  # a check, not part of the computation graph
    if not bool(torch.isfinite(cov).all()):
        raise NonFiniteError(f"{name}: contains NaN or infinite values")
    scale = cov.abs().amax(dim=(-1, -2), keepdim=True).clamp_min(1e-300)
    asym = ((cov - cov.transpose(-1, -2)).abs() / scale).amax()
    tol = 1e-6 if cov.dtype == torch.float64 else 1e-4
    if float(asym) > tol:
        raise ValueError(f"{name}: matrix is not symmetric (max relative asymmetry {float(asym):.2e})")
    with torch.no_grad():
        sym = 0.5 * (cov + cov.transpose(-1, -2))
        if semidefinite:
            eig = torch.linalg.eigvalsh(sym)
            if bool((eig < -tol * scale.squeeze(-1)).any()):
                raise ValueError(f"{name}: matrix is not positive semi-definite")
        else:
            _, info = torch.linalg.cholesky_ex(sym)
            if bool((info != 0).any()):
                raise ValueError(f"{name}: matrix is not positive definite")
    return original


def check_mask(name: str, mask: object, shape: Sequence[int]) -> Tensor:
    """Require a boolean (or 0/1) mask broadcastable-equal to ``shape``; returns a bool tensor."""
    if not isinstance(mask, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor mask, got {type(mask).__name__}")
    if tuple(mask.shape) != tuple(shape):
        raise ValueError(f"{name}: expected shape {tuple(shape)}, got {tuple(mask.shape)}")
    if mask.dtype != torch.bool:
        if torch.is_floating_point(mask) or mask.dtype in (torch.int8, torch.int16, torch.int32, torch.int64, torch.uint8):
            if not bool(((mask == 0) | (mask == 1)).all()):
                raise ValueError(f"{name}: a mask must contain only 0/1 or True/False")
            mask = mask.bool()
        else:
            raise ValueError(f"{name}: expected a boolean mask, got dtype {mask.dtype}")
    return mask


def check_same_batch(names: Sequence[str], tensors: Sequence[Tensor], n_event_dims: Sequence[int]) -> torch.Size:
    """Require the leading (batch) dims of several tensors to broadcast; return the broadcast shape."""
    shapes = [t.shape[: t.ndim - k] for t, k in zip(tensors, n_event_dims)]
    try:
        return torch.broadcast_shapes(*shapes)
    except RuntimeError as err:
        desc = ", ".join(f"{n}: {tuple(t.shape)}" for n, t in zip(names, tensors))
        raise ValueError(f"{names[0]}: batch dimensions do not broadcast ({desc})") from err


# ----------------------------------------------------------------------------- masking observations
__all__ += ["mask_observations"]


def mask_observations(obs: Tensor, mask: Tensor | None) -> Tensor:
    """``obs: (..., d)`` with every entry whose ``mask: (...)`` is False replaced by 0.

    The one way the package hides an observation from a model: ``torch.where`` (not a product),
    so a NaN or inf stored at a missing step cannot reach the model's arithmetic or its
    gradients. ``mask=None`` returns ``obs`` unchanged. The mask must have the leading shape of
    ``obs`` (bool or 0/1).
    """
    if mask is None:
        return obs
    mask = check_mask("mask", mask, tuple(obs.shape[:-1]))
    return torch.where(mask[..., None], obs, torch.zeros((), dtype=obs.dtype, device=obs.device))


_SUPPORTED_FLOAT_DTYPES = (torch.float32, torch.float64)


def check_same_dtype(names: Sequence[str], tensors: Sequence[Tensor | None]) -> torch.dtype:
    """One dtype rule for the dense Gaussian functions: every given tensor (``None`` is skipped)
    has the dtype of the first, which must be float32 or float64 (half precision cannot hold the
    covariance recursions). Raises ``ValueError`` naming the first offending argument."""
    dtype: torch.dtype | None = None
    first = ""
    for name, x in zip(names, tensors):
        if x is None:
            continue
        if x.dtype not in _SUPPORTED_FLOAT_DTYPES:
            raise ValueError(f"{name}: dtype {x.dtype} is not supported; use torch.float32 or torch.float64")
        if dtype is None:
            dtype, first = x.dtype, name
        elif x.dtype != dtype:
            raise ValueError(f"{name}: dtype {x.dtype} differs from {first}'s dtype {dtype}; "
                             "convert all inputs to one dtype")
    return dtype if dtype is not None else torch.get_default_dtype()


__all__ += ["check_same_dtype", "module_dtype", "check_input_dtype"]


def module_dtype(module: object) -> torch.dtype | None:
    """The dtype of a module's first floating-point parameter or buffer (``None`` if it has none)."""
    tensors = list(getattr(module, "parameters", lambda: [])()) + list(getattr(module, "buffers", lambda: [])())
    for t in tensors:
        if torch.is_floating_point(t):
            return t.dtype
    return None


def check_input_dtype(name: str, x: Tensor, dtype: torch.dtype | None) -> Tensor:
    """Require ``x`` to have a model's dtype ``dtype`` (skipped when ``dtype`` is None): a
    float64 tensor fed to a float32 model is an error naming ``name``, not a raw matmul error."""
    if dtype is not None and x.dtype != dtype:
        raise ValueError(f"{name}: dtype {x.dtype} differs from the model's dtype {dtype}; "
                         f"convert with {name}.to({dtype}) (or the model with .to({x.dtype}))")
    return x
