r"""The one backend table of pgm_wm (private): which implementation serves a call.

Some operations have several implementations that give the same numbers (each tested equal to
the readable reference loop in float32 and float64):

=====================================  ==========  ========  ==========  ==========
operation                              reference   tensor    compiled    parallel
=====================================  ==========  ========  ==========  ==========
``kalman_filter``                      yes         yes       yes         yes
``rts_smoother``                       yes         yes       yes         yes
``diagonal_factorized_filter``         yes         yes       yes         yes
``locally_linear_factorized_filter``   yes         no        yes         no
=====================================  ==========  ========  ==========  ==========

* ``"reference"``: the book's loop (:func:`pgm_wm.kalman.kalman_filter_reference`,
  :func:`pgm_wm.kalman.rts_smoother_reference`, :func:`pgm_wm.factorized.factorized_filter`);
* ``"tensor"``: batched tensor operations, differentiable, any device
  (:mod:`pgm_wm._backends.kalman_fast`, :func:`pgm_wm.factorized.diagonal_factorized_filter`);
* ``"compiled"``: numba loops on CPU arrays (:mod:`pgm_wm._backends.kalman_jit`: forward only;
  :mod:`pgm_wm._backends.factorized_jit`: with a hand-written backward pass);
* ``"parallel"``: the associative scan, :math:`O(\log T)` sequential depth
  (:mod:`pgm_wm.kalman_parallel`, :func:`pgm_wm.factorized.parallel_factorized_filter`).

``locally_linear_factorized_filter`` is the RKN's loop with a locally linear transition (a
softmax-weighted mixture of basis matrices, :func:`pgm_wm.rkn.locally_linear_filter`): its
reference loop runs tensor operations step by step, its compiled kernel
(:mod:`pgm_wm._backends.locally_linear_jit`) has a hand-written backward pass; it follows the
rules of ``diagonal_factorized_filter`` and falls back to its reference loop where the compiled
one cannot serve a call.

**The rules** (:func:`choose`; ``backend="auto"``, which ``"fast"`` means too):

1. ``"compiled"`` when it can serve the call, which needs all of
   (a) compiled loops switched on: the environment variable ``PGM_WM_JIT`` is not ``0``
   (read once, when this module is imported; :func:`use_compiled` overrides it) and numba is
   installed; (b) every tensor on the CPU, float32 or float64; (c) no ``torch.func`` transform
   active (``vmap``, ``grad``, ``jacrev``, ...: their wrapped tensors have no memory a
   compiled loop could read); and for the operation:
   ``kalman_filter``, ``rts_smoother``: no gradient is recorded (the loops have no backward
   pass) and the parameters are shared by the batch (unbatched ``F, H, Q, R``);
   ``diagonal_factorized_filter``, ``locally_linear_factorized_filter``: always (a gradient
   goes through the hand-written backward pass; when that backward pass must itself be
   differentiable, ``create_graph=True`` for a gradient penalty, the autograd function
   recomputes it by the tensor path, so second derivatives are exact).
2. ``"tensor"`` otherwise (``"reference"`` for an operation without a tensor path).

``"auto"`` never picks ``"reference"`` or ``"parallel"``. An explicit ``"reference"``,
``"tensor"`` or ``"parallel"`` is always served (where the operation has it); an explicit
``"compiled"`` that cannot serve the call raises ``ValueError("backend: ...")`` saying why.
The mask (``masked``) does not change the choice: with and without missing steps both
backends exist and the compiled one is faster on the CPU (``benchmarks/bench_kalman.py``).

:func:`select` describes a call from its tensors and applies :func:`choose`; callers write
``select("kalman_filter", y, F, ..., backend=backend, shared_params=...)``.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import os
from dataclasses import dataclass
from typing import Callable, Iterator, Literal

import torch
from torch import Tensor

__all__ = ["Backend", "Call", "IMPLEMENTATIONS", "REGISTRY", "choose", "compiled_available", "describe",
           "implementation", "select", "use_compiled"]

Backend = Literal["auto", "fast", "reference", "tensor", "compiled", "parallel"]

IMPLEMENTATIONS: dict[str, tuple[str, ...]] = {
    "kalman_filter": ("reference", "tensor", "compiled", "parallel"),
    "rts_smoother": ("reference", "tensor", "compiled", "parallel"),
    "diagonal_factorized_filter": ("reference", "tensor", "compiled", "parallel"),
    "locally_linear_factorized_filter": ("reference", "compiled"),
}
# The implementations with the operation's public signature, as "module:function" (imported when
# first asked for, so that no module imports another to offer it as a backend: pgm_wm.kalman
# reaches its parallel backend without importing pgm_wm.kalman_parallel, which imports it).
# "tensor" and "compiled" are reached through the operation's own function (backend=...).
REGISTRY: dict[tuple[str, str], str] = {
    ("kalman_filter", "reference"): "pgm_wm.kalman:kalman_filter_reference",
    ("kalman_filter", "parallel"): "pgm_wm.kalman_parallel:parallel_kalman_filter",
    ("rts_smoother", "reference"): "pgm_wm.kalman:rts_smoother_reference",
    ("rts_smoother", "parallel"): "pgm_wm.kalman_parallel:parallel_rts_smoother",
    ("diagonal_factorized_filter", "reference"): "pgm_wm.factorized:factorized_filter",
    ("diagonal_factorized_filter", "parallel"): "pgm_wm.factorized:parallel_factorized_filter",
    ("locally_linear_factorized_filter", "reference"): "pgm_wm.rkn:locally_linear_filter",
}
# operations whose compiled loop has a backward pass (the others serve calls without a gradient)
_COMPILED_BACKWARD = {"diagonal_factorized_filter", "locally_linear_factorized_filter"}
# operations whose compiled loop needs parameters shared by the batch
_COMPILED_SHARED_PARAMS = {"kalman_filter", "rts_smoother"}
_ALIASES = {"auto": "auto", "fast": "auto"}
_DTYPES = (torch.float32, torch.float64)


def _env_compiled() -> bool:
    """``PGM_WM_JIT`` (the one place it is read): anything but ``0``/``false``/``off``/``no``
    switches the compiled loops on."""
    return os.environ.get("PGM_WM_JIT", "1").strip().lower() not in ("0", "false", "off", "no")


_SETTINGS = {"compiled": _env_compiled()}
_NUMBA_INSTALLED: list[bool] = []           # looked up once, without importing numba


def compiled_available() -> bool:
    """Whether compiled loops may serve calls: switched on (``PGM_WM_JIT``, :func:`use_compiled`)
    and numba installed (looked up without importing it)."""
    if not _SETTINGS["compiled"]:
        return False
    if not _NUMBA_INSTALLED:
        _NUMBA_INSTALLED.append(importlib.util.find_spec("numba") is not None)
    return _NUMBA_INSTALLED[0]


@contextlib.contextmanager
def use_compiled(enabled: bool) -> Iterator[None]:
    """Within the block, switch the compiled loops on or off for ``"auto"`` (overrides
    ``PGM_WM_JIT``; for tests and for comparing the two paths in one process)."""
    old = _SETTINGS["compiled"]
    _SETTINGS["compiled"] = bool(enabled)
    try:
        yield
    finally:
        _SETTINGS["compiled"] = old


@dataclass(frozen=True)
class Call:
    """What the table looks at in a call."""

    device: str = "cpu"                 # device type of the tensors ("cpu", "cuda", "meta", ...)
    dtype: torch.dtype = torch.float64
    needs_grad: bool = False            # autograd records a graph through the inputs
    transformed: bool = False           # a torch.func transform (vmap, grad, jacrev, ...) is active
    masked: bool = False                # some steps are missing
    shared_params: bool = True          # the parameters are shared by the batch (unbatched)


def _functorch_active() -> bool:
    active = getattr(torch._C, "_are_functorch_transforms_active", None)
    return bool(active()) if active is not None else False


def describe(*tensors: Tensor | None, masked: bool = False, shared_params: bool = True,
             needs_grad: bool | None = None) -> Call:
    """The :class:`Call` of an operation on ``tensors`` (``None`` entries are skipped).
    ``needs_grad`` defaults to: gradient mode on and some tensor requires a gradient."""
    ts = [t for t in tensors if t is not None]
    devices = {t.device.type for t in ts}
    dtypes = {t.dtype for t in ts}
    if needs_grad is None:
        needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in ts)
    return Call(
        device=devices.pop() if len(devices) == 1 else ("mixed" if devices else "cpu"),
        dtype=dtypes.pop() if len(dtypes) == 1 else torch.float64 if not dtypes else torch.complex128,
        needs_grad=bool(needs_grad), transformed=_functorch_active(), masked=masked, shared_params=shared_params)


def _compiled_obstacle(op: str, call: Call) -> str | None:
    """Why the compiled loop cannot serve ``call`` (None: it can)."""
    if not _SETTINGS["compiled"]:
        return "compiled loops are switched off (PGM_WM_JIT=0)"
    if not compiled_available():
        return "numba is not installed"
    if call.device != "cpu":
        return f"the tensors are on {call.device!r}, compiled loops run on the CPU"
    if call.dtype not in _DTYPES:
        return f"dtype {call.dtype} (compiled loops take float32 or float64)"
    if call.transformed:
        return "a torch.func transform is active (use the tensor backend)"
    if op not in _COMPILED_BACKWARD and call.needs_grad:
        return "a gradient is recorded and the compiled loop has no backward pass"
    if op in _COMPILED_SHARED_PARAMS and not call.shared_params:
        return "the parameters are batched (the compiled loop takes one F, H, Q, R)"
    return None


def choose(op: str, call: Call, backend: str = "auto") -> str:
    """The implementation of ``op`` that serves ``call`` (rules in the module docstring):
    ``"reference"``, ``"tensor"``, ``"compiled"`` or ``"parallel"``."""
    if op not in IMPLEMENTATIONS:
        raise ValueError(f"op: unknown operation {op!r}; known: {', '.join(IMPLEMENTATIONS)}")
    impls = IMPLEMENTATIONS[op]
    name = _ALIASES.get(backend, backend)
    if name not in impls and name != "auto":
        allowed = ", ".join(repr(b) for b in ("auto", "fast") + impls)
        raise ValueError(f"backend: expected one of {allowed} for {op}, got {backend!r}")
    if name in ("reference", "tensor", "parallel"):
        return name
    obstacle = _compiled_obstacle(op, call)
    if name == "compiled" and obstacle is not None:
        raise ValueError(f"backend: 'compiled' cannot serve this call of {op}: {obstacle}")
    if obstacle is None:
        return "compiled"
    return "tensor" if "tensor" in impls else "reference"


def select(op: str, *tensors: Tensor | None, backend: str = "auto", masked: bool = False,
           shared_params: bool = True, needs_grad: bool | None = None) -> str:
    """:func:`choose` for a call on ``tensors`` (:func:`describe`)."""
    if backend in ("reference", "tensor", "parallel"):      # no need to look at the tensors
        return choose(op, Call(), backend)
    return choose(op, describe(*tensors, masked=masked, shared_params=shared_params, needs_grad=needs_grad),
                  backend)


def implementation(op: str, name: str) -> Callable:
    """The function registered for ``(op, name)`` in :data:`REGISTRY` (imported on first use)."""
    try:
        target = REGISTRY[(op, name)]
    except KeyError:
        raise ValueError(f"backend: no registered implementation {name!r} of {op}") from None
    module, function = target.split(":")
    return getattr(importlib.import_module(module), function)
