"""Shared strategies and helpers of the fuzz suite (``tests/test_fuzz_*.py``, issue 13).

Values come from a hypothesis-drawn seed (fast, reproducible); shapes, dtypes, scales and the
kind of corruption are drawn by hypothesis itself, so a failure shrinks to a small case."""

from __future__ import annotations

import re
from typing import Callable

import pytest
import torch
from hypothesis import settings
from hypothesis import strategies as st

FUZZ = settings(max_examples=12, deadline=None, derandomize=True)
FUZZ_SLOW = settings(max_examples=5, deadline=None, derandomize=True)

dtypes = st.sampled_from([torch.float32, torch.float64])
bad_dtypes = st.sampled_from([torch.float16, torch.bfloat16])
seeds = st.integers(0, 2**31 - 1)


def gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def randn(g: torch.Generator, *shape: int, dtype: torch.dtype = torch.float64, scale: float = 1.0) -> torch.Tensor:
    return scale * torch.randn(*shape, generator=g, dtype=torch.float64).to(dtype)


def spd(g: torch.Generator, n: int, dtype: torch.dtype, scale: float = 1.0, batch: tuple = ()) -> torch.Tensor:
    a = torch.randn(*batch, n, n, generator=g, dtype=torch.float64)
    return (scale * (a @ a.transpose(-1, -2) / n + 0.1 * torch.eye(n, dtype=torch.float64))).to(dtype)


def pos(g: torch.Generator, *shape: int, dtype: torch.dtype = torch.float64, lo: float = 0.05) -> torch.Tensor:
    return (lo + torch.rand(*shape, generator=g, dtype=torch.float64) * 2.0).to(dtype)


def other(dtype: torch.dtype) -> torch.dtype:
    return torch.float64 if dtype == torch.float32 else torch.float32


def raises_named(name: str | tuple[str, ...], fn: Callable[[], object]) -> None:
    """``fn()`` raises a ValueError whose message starts with ``name`` (or one of the names:
    a mismatch between two arguments, e.g. mixed dtypes, may be reported at either)."""
    names = (name,) if isinstance(name, str) else name
    with pytest.raises(ValueError, match="^(" + "|".join(re.escape(n) for n in names) + ")"):
        fn()


def finite(*xs: torch.Tensor) -> bool:
    return all(bool(torch.isfinite(x).all()) for x in xs)


def psd(cov: torch.Tensor) -> bool:
    """Symmetric and positive semi-definite to the dtype's rounding."""
    c = cov.detach().to(torch.float64)
    tol = 1e-5 if cov.dtype == torch.float32 else 1e-10
    scale = c.abs().amax(dim=(-1, -2)).clamp_min(1e-30)
    sym = ((c - c.transpose(-1, -2)).abs().amax(dim=(-1, -2)) <= tol * 10 * scale).all()
    eig = torch.linalg.eigvalsh(0.5 * (c + c.transpose(-1, -2)))
    return bool(sym) and bool((eig >= -tol * scale[..., None]).all())


def corrupt(x: torch.Tensor, kind: str) -> torch.Tensor:
    """An invalid version of a valid float tensor."""
    x = x.clone()
    if kind == "nan":
        x.view(-1)[0] = float("nan")
    elif kind == "inf":
        x.view(-1)[-1] = float("inf")
    elif kind == "float16":
        x = x.to(torch.float16)
    elif kind == "bfloat16":
        x = x.to(torch.bfloat16)
    elif kind == "mixed":
        x = x.to(other(x.dtype))
    elif kind == "int":
        x = x.round().to(torch.int64)
    elif kind == "shape":
        x = torch.cat([x, x[..., :1]], dim=-1)
    else:  # pragma: no cover
        raise AssertionError(kind)
    return x


VALUE_KINDS = ["nan", "inf"]
DTYPE_KINDS = ["float16", "bfloat16", "mixed"]
ALL_KINDS = VALUE_KINDS + DTYPE_KINDS + ["shape"]
