"""Compiled loops by numba, compiled on first call (never at import).

The fast paths of :func:`pgm_wm.kalman.kalman_filter`, :func:`pgm_wm.kalman.rts_smoother` and
:func:`pgm_wm.factorized.diagonal_factorized_filter` spend their time on the cost of launching
one tensor operation per step (a few microseconds each, whatever the size of the batch), not on
arithmetic. Where numba is installed, those loops run as compiled code instead: one pass over
the sequences, the small matrices of a step in registers, written like the equations of the
book (:mod:`pgm_wm._backends.kalman_jit`, :mod:`pgm_wm._backends.factorized_jit`). Whether a
call uses them is decided by the backend table (:mod:`pgm_wm._backends`), not here.

``@kernel`` marks such a loop. It stays a plain Python function until its first call:

* importing a module of kernels imports nothing from numba, compiles nothing and writes
  nothing (``PGM_WM_JIT=0`` therefore never touches numba);
* the first call compiles it with ``numba.njit`` (kernels it calls first), cached on disk where
  numba finds a writable place (``NUMBA_CACHE_DIR`` if set, else ``__pycache__`` next to the
  sources, else the per-user cache directory, e.g. ``~/.cache/numba``) and in memory for the
  process where none is writable (a read-only install without a writable home);
* the first time a process compiles (no cache file yet), one line on stderr says so;
* a cache file that cannot be read (truncated, garbled, from an interrupted write) is detected
  when the loop is loaded: the cache of that loop and of the loops it calls is emptied and the
  loop compiled again, once per process (a line on stderr says so).
"""

from __future__ import annotations

import functools
import os
import sys
import threading
import types
from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor

_LOCK = threading.RLock()
_ANNOUNCED = False            # the one line "compiling ..." was printed in this process


def _numba() -> Any:
    """The numba module, imported on the first compile only."""
    import numba

    return numba


def _say(text: str) -> None:
    print(f"pgm_wm: {text}", file=sys.stderr, flush=True)


class Kernel:
    """A loop compiled by ``numba.njit`` on its first call (module docstring). Calling it
    runs the compiled code; ``py_func`` is the plain Python function."""

    def __init__(self, fn: Callable) -> None:
        self.py_func = fn
        self._dispatcher: Any = None
        self._repaired = False
        functools.update_wrapper(self, fn)

    def _dependencies(self) -> dict[str, "Kernel"]:
        """The kernels this one calls (module globals it names that are kernels)."""
        g = self.py_func.__globals__
        return {n: g[n] for n in self.py_func.__code__.co_names if isinstance(g.get(n), Kernel)}

    def dispatcher(self) -> Any:
        """The numba dispatcher (created on first use, those of the kernels it calls first)."""
        if self._dispatcher is None:
            with _LOCK:
                if self._dispatcher is None:
                    self._dispatcher = self._make()
        return self._dispatcher

    def _make(self) -> Any:
        numba = _numba()
        fn = self.py_func
        deps = {name: k.dispatcher() for name, k in self._dependencies().items()}
        if deps:      # numba resolves the callees from the globals: give it their dispatchers
            fn = types.FunctionType(fn.__code__, {**fn.__globals__, **deps}, fn.__name__, fn.__defaults__,
                                    fn.__closure__)
            fn.__qualname__ = self.py_func.__qualname__
        options = dict(nogil=True, fastmath=False)
        try:
            disp = numba.njit(cache=True, **options)(fn)
        except RuntimeError:          # "cannot cache function ...: no locator available": nowhere writable
            disp = numba.njit(cache=False, **options)(fn)
        return disp

    def cache_dir(self) -> str | None:
        """Where numba caches this loop (None: in memory only)."""
        return getattr(getattr(self.dispatcher(), "_cache", None), "cache_path", None)

    def _index_exists(self) -> bool:
        try:
            return os.path.exists(self.dispatcher()._cache._cache_file._index_path)
        except AttributeError:          # in memory, or another numba: no index file to look at
            return False

    def _announce(self) -> None:
        """The one line of the first compile in this process (only when no cache file exists)."""
        global _ANNOUNCED
        if _ANNOUNCED or self._index_exists():
            return
        _ANNOUNCED = True
        where = self.cache_dir()
        place = f"cached in {where}" if where else "kept in memory: no writable cache directory"
        _say(f"compiling the loop '{self.__name__}' with numba on its first use (can take a minute; {place}); "
             "PGM_WM_JIT=0 runs tensor operations instead")

    def _flush(self, seen: set[int]) -> None:
        """Empty the disk cache of this loop and of the loops it calls."""
        if id(self) in seen:
            return
        seen.add(id(self))
        cache = getattr(self.dispatcher(), "_cache", None)
        if cache is not None:
            try:
                cache.flush()
            except OSError:      # the cache became unwritable: compile in memory instead
                cache.disable()
        for k in self._dependencies().values():
            k._flush(seen)

    def __call__(self, *args: Any) -> Any:
        disp = self.dispatcher()
        if not disp.signatures:
            self._announce()
        try:
            return disp(*args)
        except Exception as err:            # noqa: BLE001 - an unreadable cache file, see the module docstring
            if self._repaired or self.cache_dir() is None or type(err).__module__.startswith("numba"):
                raise                       # numba's own errors (typing, lowering) are not the cache's
            self._repaired = True
            _say(f"the numba cache of '{self.__name__}' in {self.cache_dir()} could not be loaded "
                 f"({type(err).__name__}: {err}); rebuilding it")
            self._flush(set())
            return disp(*args)


def kernel(fn: Callable) -> Kernel:
    """Mark ``fn`` as a compiled loop (compiled by numba on first call; module docstring)."""
    return Kernel(fn)


def as_array(x: Tensor) -> np.ndarray:
    """A NumPy view of a CPU tensor (no copy, strides kept; detached)."""
    return x.detach().numpy()


def empty(*shape: int, dtype: torch.dtype) -> Tensor:
    """An uninitialized CPU tensor allocated by NumPy, which asks the kernel for transparent
    huge pages for large buffers: far fewer page faults when a loop first writes its outputs
    (on a machine without them, the same as ``torch.empty``)."""
    return torch.from_numpy(np.empty(shape, dtype=_NUMPY_DTYPES[dtype]))


_NUMPY_DTYPES = {torch.float32: np.float32, torch.float64: np.float64}


def contiguous_array(x: Tensor) -> np.ndarray:
    """A C-contiguous NumPy array of a CPU tensor (a view where the tensor is contiguous)."""
    return np.ascontiguousarray(x.detach().numpy())
