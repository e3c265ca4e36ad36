"""Compiled loops for the fast backends (Chapters 1 and 6), by numba.

The fast paths of :func:`pgm_wm.kalman.kalman_filter`, :func:`pgm_wm.kalman.rts_smoother` and
:func:`pgm_wm.factorized.diagonal_factorized_filter` spend their time on the cost of launching
one tensor operation per step (a few microseconds each, whatever the size of the batch), not
on arithmetic. Where numba is installed, those loops run as compiled code instead: one pass
over the sequences, the small matrices of a step in registers, written like the equations of
the book (see :mod:`pgm_wm.kalman_jit` and :mod:`pgm_wm.factorized_jit`).

``enabled(*tensors)`` says whether the compiled loops serve a call: numba importable, the
tensors on the CPU, and the environment variable ``PGM_WM_JIT`` not set to ``0``. Everything
else (another device, no numba) runs the tensor-operation paths, tested equal to the same
reference loops. Compiled code is cached on disk next to the sources (numba's ``cache=True``),
so only the first run on a machine pays the compile time (a few seconds).
"""

from __future__ import annotations

import os
from typing import Callable

import numpy as np
import torch
from torch import Tensor

try:                                                   # an optional speed-up: never required
    import numba
except ImportError:                                    # pragma: no cover - numba is pinned
    numba = None


def jit(fn: Callable) -> Callable:
    """``fn`` compiled by ``numba.njit`` (cached on disk), or ``fn`` itself without numba."""
    if numba is None:                                  # pragma: no cover
        return fn
    return numba.njit(cache=True, nogil=True, fastmath=False)(fn)


def enabled(*tensors: Tensor) -> bool:
    """True when the compiled loops can serve tensors ``tensors`` (see the module docstring)."""
    if numba is None or os.environ.get("PGM_WM_JIT", "1") == "0":
        return False
    return all(t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) for t in tensors)


def as_array(x: Tensor) -> np.ndarray:
    """A NumPy view of a CPU tensor (no copy, strides kept; detached)."""
    return x.detach().numpy()
