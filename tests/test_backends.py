"""The backend table (issue 20, item 3) and the compiled loops as users get them (issue 24,
items 3 and 4).

* The table's choice for each (device, gradient, dtype, mask, torch.func transform, batched
  parameters) case, against the rules written in :mod:`pgm_wm._backends` (typed in below
  case by case, not recomputed by the same code), and what an explicit ``backend=`` does.
* Every backend of every operation that has several gives the reference loop's numbers in
  float32 and float64 (the Kalman compiled/tensor paths in detail: test_kalman_backends.py;
  the diagonal factorized filter: test_filtering.py; the scans: test_kalman_parallel.py).
* Second derivatives (a gradient penalty, ``create_graph=True``) through the compiled diagonal
  factorized filter (the MTS3 fast level) equal those of the tensor path; ``torch.func.jacrev``
  works and equals the reference loop's Jacobian.
* Importing any module compiles nothing and writes nothing; a read-only install with no
  writable home imports every module and runs a masked filter compiled in memory;
  ``PGM_WM_JIT=0`` never imports numba; an unreadable cache file is rebuilt.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from functools import partial
from pathlib import Path

import pytest
import torch

import pgm_wm
from pgm_wm import _backends
from pgm_wm._backends import Call, choose, select, use_compiled
from pgm_wm.beliefs import DiagGaussian, FactorizedBelief
from pgm_wm.factorized import diagonal_factorized_filter, factorized_filter
from pgm_wm.gaussian import Gaussian
from pgm_wm.kalman import kalman_filter, kalman_filter_reference, rts_smoother, rts_smoother_reference

needs_numba = pytest.mark.skipif(not _backends.compiled_available(), reason="numba not installed or PGM_WM_JIT=0")
F64, F32 = torch.float64, torch.float32
DENSE = ("kalman_filter", "rts_smoother")
FACTORIZED = ("diagonal_factorized_filter", "locally_linear_factorized_filter")


# ----------------------------------------------------------------------------- the table's rules
# (operation kind, call, expected choice of "auto" with compiled loops on). The rules of the
# module docstring, case by case.
CASES = [
    # CPU, float64/float32, no gradient: compiled, with and without a mask
    ("dense", Call("cpu", F64, needs_grad=False, masked=False), "compiled"),
    ("dense", Call("cpu", F64, needs_grad=False, masked=True), "compiled"),
    ("dense", Call("cpu", F32, needs_grad=False, masked=True), "compiled"),
    ("factorized", Call("cpu", F64, needs_grad=False, masked=False), "compiled"),
    ("factorized", Call("cpu", F32, needs_grad=False, masked=True), "compiled"),
    # a gradient: the dense loops have no backward pass, the factorized one has
    ("dense", Call("cpu", F64, needs_grad=True, masked=False), "tensor"),
    ("dense", Call("cpu", F32, needs_grad=True, masked=True), "tensor"),
    ("factorized", Call("cpu", F64, needs_grad=True, masked=True), "compiled"),
    ("factorized", Call("cpu", F32, needs_grad=True, masked=False), "compiled"),
    # another device: tensor operations
    ("dense", Call("cuda", F32, needs_grad=False, masked=True), "tensor"),
    ("dense", Call("meta", F64, needs_grad=False, masked=False), "tensor"),
    ("factorized", Call("cuda", F32, needs_grad=True, masked=True), "tensor"),
    ("factorized", Call("mps", F32, needs_grad=False, masked=False), "tensor"),
    # other dtypes: tensor operations
    ("dense", Call("cpu", torch.bfloat16, needs_grad=False), "tensor"),
    ("factorized", Call("cpu", torch.float16, needs_grad=False), "tensor"),
    # a torch.func transform: tensor operations
    ("dense", Call("cpu", F64, needs_grad=False, transformed=True), "tensor"),
    ("factorized", Call("cpu", F64, needs_grad=True, transformed=True), "tensor"),
    # batched parameters: the dense compiled loops take one F, H, Q, R
    ("dense", Call("cpu", F64, needs_grad=False, shared_params=False), "tensor"),
    ("factorized", Call("cpu", F64, needs_grad=False, shared_params=False), "compiled"),
]


@pytest.mark.parametrize("kind, call, expected", CASES)
@pytest.mark.parametrize("backend", ["auto", "fast"])
def test_table_choice_for_each_case(kind, call, expected, backend):
    with use_compiled(True):
        if not _backends.compiled_available():
            pytest.skip("numba is not installed")
        for op in DENSE if kind == "dense" else FACTORIZED:
            assert choose(op, call, backend) == _fallback(op, expected), (op, call)
    with use_compiled(False):        # PGM_WM_JIT=0: never compiled
        for op in DENSE if kind == "dense" else FACTORIZED:
            assert choose(op, call, backend) == _fallback(op, "tensor"), (op, call)


def _fallback(op, name):
    """The locally linear filter has no tensor path: its fallback is the book's loop."""
    return "reference" if name == "tensor" and "tensor" not in _backends.IMPLEMENTATIONS[op] else name


@pytest.mark.parametrize("kind, call, expected", CASES)
def test_explicit_backends(kind, call, expected):
    """``reference``/``tensor``/``parallel`` are always served where the operation has them;
    ``compiled`` is served where ``auto`` would pick it and is otherwise a ValueError naming
    ``backend`` and the reason."""
    with use_compiled(True):
        if not _backends.compiled_available():
            pytest.skip("numba is not installed")
        for op in DENSE if kind == "dense" else FACTORIZED:
            assert choose(op, call, "reference") == "reference"
            if "tensor" in _backends.IMPLEMENTATIONS[op]:
                assert choose(op, call, "tensor") == "tensor"
            if expected == "compiled":
                assert choose(op, call, "compiled") == "compiled"
            else:
                with pytest.raises(ValueError, match="^backend: 'compiled' cannot serve"):
                    choose(op, call, "compiled")
    assert choose("kalman_filter", Call(), "parallel") == "parallel"
    with pytest.raises(ValueError, match="^backend"):
        choose("locally_linear_factorized_filter", Call(), "parallel")
    with pytest.raises(ValueError, match="^backend"):
        choose("kalman_filter", Call(), "gpu")
    with pytest.raises(ValueError, match="^op"):
        choose("no_such_operation", Call())


def test_describe_reads_the_call_from_the_tensors():
    x = torch.zeros(3, dtype=F32)
    w = torch.zeros(3, dtype=F32, requires_grad=True)
    call = _backends.describe(x, None, w, masked=True)
    assert (call.device, call.dtype, call.needs_grad, call.masked, call.transformed) == ("cpu", F32, True, True, False)
    with torch.no_grad():
        assert not _backends.describe(x, w).needs_grad
    assert _backends.describe(torch.zeros(2, device="meta")).device == "meta"
    assert _backends.describe(x, x.double()).dtype not in (F32, F64)      # mixed dtypes: not compiled
    seen = []
    torch.func.vmap(lambda v: seen.append(_backends.describe(v).transformed) or v)(torch.zeros(2, 3))
    assert seen == [True]
    with use_compiled(True):
        if _backends.compiled_available():
            assert select("kalman_filter", x, x) == "compiled"
            assert select("kalman_filter", x, w) == "tensor"                     # a gradient
            assert select("diagonal_factorized_filter", x, w) == "compiled"      # own backward pass


# ---------------------------------------------------------------- every backend = the reference


def _dense(dtype, mask_kind="per_sequence", seed=0):
    g = torch.Generator().manual_seed(seed)
    n, m, N, T = 3, 2, 4, 25
    F = 0.9 * torch.linalg.qr(torch.randn(n, n, generator=g, dtype=F64))[0]
    H = torch.randn(m, n, generator=g, dtype=F64)
    Q, R = 0.1 * torch.eye(n, dtype=F64), 0.5 * torch.eye(m, dtype=F64)
    y = torch.randn(N, T, m, generator=g, dtype=F64)
    mask = {"per_sequence": torch.rand(N, T, generator=g) > 0.3, "none": None}[mask_kind]
    init = Gaussian(torch.zeros(n, dtype=F64), torch.eye(n, dtype=F64))
    return [x.to(dtype) for x in (y,)] + [init.to(dtype)] + [x.to(dtype) for x in (F, H, Q, R)] + [mask]


@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("mask_kind", ["per_sequence", "none"])
@pytest.mark.parametrize("backend", ["auto", "fast", "reference", "tensor", "compiled", "parallel"])
def test_every_kalman_backend_equals_the_reference(dtype, mask_kind, backend):
    if backend == "compiled" and not _backends.compiled_available():
        pytest.skip("numba is not installed")
    y, init, F, H, Q, R, mask = _dense(dtype, mask_kind)
    ref = kalman_filter_reference(y, init, F, H, Q, R, mask)
    res = kalman_filter(y, init, F, H, Q, R, mask, backend=backend)
    tol = dict(rtol=1e-10, atol=1e-10) if dtype == F64 else dict(rtol=2e-4, atol=2e-4)
    for f in ("prior", "posterior", "next_prior"):
        torch.testing.assert_close(getattr(res, f).mean, getattr(ref, f).mean, **tol)
        torch.testing.assert_close(getattr(res, f).cov, getattr(ref, f).cov, **tol)
    torch.testing.assert_close(res.log_likelihoods, ref.log_likelihoods, **tol)
    sm_ref = rts_smoother_reference(ref, F, Q)
    sm = rts_smoother(res, F, Q, backend=backend)
    torch.testing.assert_close(sm.mean, sm_ref.mean, **tol)
    torch.testing.assert_close(sm.cov, sm_ref.cov, **tol)


@needs_numba
def test_explicit_compiled_kalman_refuses_what_it_cannot_serve():
    y, init, F, H, Q, R, mask = _dense(F64)
    Fg = F.clone().requires_grad_(True)
    with pytest.raises(ValueError, match="^backend: 'compiled' cannot serve .*gradient"):
        kalman_filter(y, init, Fg, H, Q, R, mask, backend="compiled")
    with pytest.raises(ValueError, match="^backend: 'compiled' cannot serve .*batched"):
        kalman_filter(y, init, F.expand(4, 3, 3), H, Q, R, mask, backend="compiled")
    with use_compiled(False), pytest.raises(ValueError, match="^backend: 'compiled' cannot serve .*PGM_WM_JIT"):
        kalman_filter(y, init, F, H, Q, R, mask, backend="compiled")
    res = kalman_filter(y, init, F, H, Q, R, mask)
    with pytest.raises(ValueError, match="^backend"):
        rts_smoother(res, F, Q, backend="gpu")  # type: ignore[arg-type]


def _factorized(dtype, B=3, T=12, m=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g, dtype=F64)  # noqa: E731
    eye = torch.eye(m, dtype=F64)
    A = torch.cat([torch.cat([torch.diag(0.9 + 0.05 * r(m)), torch.diag(0.1 * r(m))], 1),
                   torch.cat([torch.diag(0.1 * r(m)), torch.diag(0.8 + 0.05 * r(m))], 1)], 0)
    prior = FactorizedBelief(r(B, 2 * m), 1.0 + r(B, m).abs(), 1.0 + r(B, m).abs(), 0.1 * torch.tanh(r(B, m)))
    obs = DiagGaussian(r(B, T, m), 0.2 + r(B, T, m).abs())
    inputs = FactorizedBelief(0.1 * r(B, T, 2 * m), 0.01 * r(B, T, m).abs(), 0.01 * r(B, T, m).abs(),
                              torch.zeros(B, T, m, dtype=F64))
    mask = torch.rand(B, T, generator=g) > 0.3
    q = 0.05 + 0.01 * r(2 * m).abs()
    del eye
    cast = lambda b: b.map(lambda x: x.to(dtype))  # noqa: E731
    return cast(prior), A.to(dtype), q.to(dtype), cast(obs), mask, cast(inputs)


@pytest.mark.parametrize("dtype", [F64, F32])
@pytest.mark.parametrize("backend", ["auto", "fast", "reference", "tensor", "compiled", "parallel"])
def test_every_diagonal_factorized_backend_equals_the_reference(dtype, backend):
    if backend == "compiled" and not _backends.compiled_available():
        pytest.skip("numba is not installed")
    prior, A, q, obs, mask, inputs = _factorized(dtype)
    ref = factorized_filter(prior, A, q, obs, mask, inputs)
    res = diagonal_factorized_filter(prior, A, q, obs, mask, inputs, backend=backend)
    tol = dict(rtol=1e-10, atol=1e-12) if dtype == F64 else dict(rtol=2e-4, atol=2e-5)
    for f in ("prior", "posterior", "next_prior"):
        for x, y in zip(getattr(res, f)._tensors(), getattr(ref, f)._tensors()):
            torch.testing.assert_close(x, y, **tol)


# ------------------------------------------------------------------- higher-order gradients


def _penalized_grads(backend: str, dtype=F64):
    """Gradients of ``loss + |d loss / d params|^2`` (a gradient penalty: the backward pass is
    itself differentiated) through the diagonal factorized filter."""
    prior, A, q, obs, mask, inputs = _factorized(dtype)
    leaves = [A.clone().requires_grad_(True), q.clone().requires_grad_(True), obs.mean.clone().requires_grad_(True),
              obs.var.clone().requires_grad_(True), prior.mean.clone().requires_grad_(True)]
    A_, q_, w_, v_, z0 = leaves
    res = diagonal_factorized_filter(FactorizedBelief(z0, prior.var_upper, prior.var_lower, prior.cov_side), A_, q_,
                                     DiagGaussian(w_, v_), mask, inputs, backend=backend)
    loss = (res.posterior.mean.square().sum() + res.next_prior.var_upper.log().sum()
            + res.posterior.var_lower.sum())
    first = torch.autograd.grad(loss, leaves, create_graph=True)
    penalty = sum(g.square().sum() for g in first)
    return torch.autograd.grad(loss + penalty, leaves)


@needs_numba
@pytest.mark.parametrize("dtype", [F64, F32])
def test_gradient_penalty_through_the_compiled_filter_equals_the_tensor_path(dtype):
    """Before: the compiled loop's backward pass was not differentiable, so a gradient penalty
    lost its second-order terms silently (issue 24: 0.0008 instead of 1.46)."""
    compiled = _penalized_grads("compiled", dtype)
    tensor = _penalized_grads("tensor", dtype)
    reference = _penalized_grads("reference", dtype)
    tol = dict(rtol=1e-9, atol=1e-10) if dtype == F64 else dict(rtol=1e-3, atol=1e-4)
    for c, t in zip(compiled, tensor):
        torch.testing.assert_close(c, t, **tol)
    # the reference loop treats A as a full matrix: its second derivatives with respect to
    # entries off the block diagonals differ (a transition with diagonal blocks has none)
    m = compiled[0].shape[0] // 2
    block_diagonals = torch.eye(m, dtype=torch.bool).repeat(2, 2)
    torch.testing.assert_close(tensor[0][block_diagonals], reference[0][block_diagonals], **tol)
    for t, r in zip(tensor[1:], reference[1:]):
        torch.testing.assert_close(t, r, **tol)


@needs_numba
def test_gradient_penalty_through_the_mts3_fast_level_is_the_same_compiled_or_not():
    """The issue's reproducer: MTS3 (its fast level runs the diagonal factorized filter), a
    gradient penalty with ``create_graph=True``; every parameter's gradient compiled equals the
    one with the compiled loops switched off (``PGM_WM_JIT=0``)."""
    from pgm_wm.mts3 import build_mts3

    grads = {}
    for compiled in (True, False):
        torch.manual_seed(0)
        model = build_mts3(3, 2, 4, 5, (8,)).double()
        g = torch.Generator().manual_seed(1)
        obs, act = torch.randn(2, 20, 3, generator=g, dtype=F64), torch.randn(2, 20, 2, generator=g, dtype=F64)
        mask = torch.rand(2, 20, generator=g) > 0.2
        with use_compiled(compiled):
            mean, var = model(obs, act, mask)
            loss = ((mean - obs).square() / var + var.log()).mean()
            params = [p for p in model.parameters() if p.requires_grad]
            first = torch.autograd.grad(loss, params, create_graph=True, allow_unused=True)
            penalty = sum(f.square().sum() for f in first if f is not None)
            (loss + penalty).backward()
        grads[compiled] = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
    assert grads[True].keys() == grads[False].keys()
    assert any("basis_11" in n for n in grads[True])
    for name in grads[True]:
        torch.testing.assert_close(grads[True][name], grads[False][name], rtol=1e-8, atol=1e-10, msg=name)


def test_jacrev_through_the_diagonal_filter_equals_the_reference():
    """``torch.func`` transforms are served by the tensor path (the table), so ``jacrev`` works
    and equals the Jacobian of the reference loop; the compiled autograd function called
    directly under a transform raises a ValueError naming ``backend``."""
    prior, A, q, obs, mask, inputs = _factorized(F64, B=2, T=5, m=2)

    def f(fn, w):
        return fn(prior, A, q, DiagGaussian(w, obs.var), mask, inputs).posterior.mean

    jac = torch.func.jacrev(partial(f, diagonal_factorized_filter))(obs.mean)
    ref = torch.autograd.functional.jacobian(partial(f, factorized_filter), obs.mean)
    torch.testing.assert_close(jac, ref, rtol=1e-10, atol=1e-12)
    if _backends.compiled_available():
        from pgm_wm._backends.factorized_jit import diagonal_filter_jit

        def direct(w):
            N, T, m = w.shape
            z = torch.zeros(N, T, 2 * m, dtype=F64)
            return diagonal_filter_jit(torch.zeros(N, 2 * m, dtype=F64), torch.ones(N, 3 * m, dtype=F64), w,
                                       torch.ones_like(w), None, z, torch.ones(N, T, 3 * m, dtype=F64), A,
                                       torch.ones(3, 3, m, dtype=F64))[0]

        with pytest.raises(ValueError, match="^backend"):
            torch.func.jacrev(direct)(obs.mean)


# ------------------------------------------------------------- imports, caches, read-only installs

PACKAGE = Path(pgm_wm.__file__).resolve().parent
IMPORT_ALL = textwrap.dedent("""
    import importlib, pkgutil, sys
    import pgm_wm
    for info in pkgutil.walk_packages(pgm_wm.__path__, "pgm_wm."):
        if not info.name.endswith("__main__"):
            importlib.import_module(info.name)
    assert "numba" not in sys.modules, "importing pgm_wm imported numba"
""")
MASKED_FILTER = textwrap.dedent("""
    import torch
    from pgm_wm.gaussian import Gaussian
    from pgm_wm.kalman import kalman_filter, kalman_filter_reference
    g = torch.Generator().manual_seed(0)
    y = torch.randn(3, 15, 2, generator=g, dtype=torch.float64)
    mask = torch.rand(3, 15, generator=g) > 0.3
    eye = torch.eye(2, dtype=torch.float64)
    args = (y, Gaussian(torch.zeros(2, dtype=torch.float64), eye), 0.9 * eye, eye, 0.1 * eye, eye, mask)
    res = kalman_filter(*args, backend=BACKEND)
    ref = kalman_filter_reference(*args)
    torch.testing.assert_close(res.posterior.mean, ref.posterior.mean, rtol=1e-10, atol=1e-10)
    print("numba imported:", "numba" in sys.modules)
""")


def _clean_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME", "PGM_WM_JIT", "PYTHONPATH")}
    env.update(extra)
    return env


def _files(root: Path) -> dict[str, int]:
    return {str(p.relative_to(root)): p.stat().st_size for p in root.rglob("*")}


def test_importing_every_module_compiles_and_writes_nothing(tmp_path):
    """A writable copy of the package: importing every module (no bytecode files, to see the
    rest) leaves the tree unchanged and does not import numba."""
    site = tmp_path / "site"
    shutil.copytree(PACKAGE, site / "pgm_wm", ignore=shutil.ignore_patterns("__pycache__"))
    before = _files(site)
    env = _clean_env(PYTHONPATH=str(site), PYTHONDONTWRITEBYTECODE="1", NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    subprocess.run([sys.executable, "-c", IMPORT_ALL], env=env, cwd=tmp_path, check=True, timeout=600)
    assert _files(site) == before
    assert not (tmp_path / "numba").exists()


@pytest.mark.parametrize("jit", ["1", "0"])
def test_read_only_install_without_a_writable_home(tmp_path, jit):
    """A read-only copy of the package and no writable home (issue 24: ``import pgm_wm.mts3``
    raised "cannot cache function ...: no locator available"): every module imports, and a
    masked Kalman filter runs, compiled in memory (``PGM_WM_JIT=1``, the compiled backend
    forced) or without ever importing numba (``PGM_WM_JIT=0``)."""
    site = tmp_path / "site"
    shutil.copytree(PACKAGE, site / "pgm_wm", ignore=shutil.ignore_patterns("__pycache__"))
    home = site / "home"                      # does not exist, inside the read-only tree
    backend = '"compiled"' if jit == "1" else '"auto"'
    script = "import sys\n" + IMPORT_ALL + MASKED_FILTER.replace("BACKEND", backend)
    if jit == "1" and not _backends.compiled_available():
        pytest.skip("numba is not installed")
    env = _clean_env(PYTHONPATH=str(site), HOME=str(home), PGM_WM_JIT=jit, MPLCONFIGDIR=str(tmp_path / "mpl"))
    cmd = [sys.executable, "-c", script]
    if os.geteuid() == 0:      # root ignores permission bits: a read-only bind mount in a mount namespace
        if shutil.which("unshare") is None:
            pytest.skip("running as root without unshare: cannot make the copy read-only")
        probe = subprocess.run(["unshare", "-m", "true"], capture_output=True)
        if probe.returncode != 0:
            pytest.skip("running as root and unshare -m is not permitted: cannot make the copy read-only")
        cmd = ["unshare", "-m", "sh", "-c", 'mount --bind -o ro "$0" "$0" && exec "$@"', str(site), *cmd]
    else:
        subprocess.run(["chmod", "-R", "a-w", str(site)], check=True)
    before = _files(site)
    try:
        out = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=900)
    finally:
        subprocess.run(["chmod", "-R", "u+w", str(site)], check=False)
    assert out.returncode == 0, out.stderr[-3000:]
    assert _files(site) == before
    if jit == "0":
        assert "numba imported: False" in out.stdout
    else:
        assert "numba imported: True" in out.stdout
        assert "kept in memory" in out.stderr            # the one line of the first compile
        assert out.stderr.count("pgm_wm: compiling") == 1


CACHED_KERNEL = textwrap.dedent("""
    import numpy as np
    from pgm_wm._backends.kalman_jit import _same
    a = np.zeros((2, 2, 3))
    assert _same(a, a) and not _same(a, a + 1.0)
    print("cache:", _same.cache_dir())
""")


@needs_numba
@pytest.mark.parametrize("damage", ["truncate index", "truncate data", "garble index"])
def test_an_unreadable_cache_file_is_rebuilt(tmp_path, damage):
    """Issue 24: a truncated or garbled numba cache file made every later run fail until
    ``__pycache__/*.nb*`` was deleted. Now the loop is compiled again (one line says so) and
    later runs load the rebuilt cache silently."""
    cache = tmp_path / "numba"
    env = _clean_env(NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(PACKAGE.parent))
    run = lambda: subprocess.run([sys.executable, "-c", CACHED_KERNEL], env=env, cwd=tmp_path,  # noqa: E731
                                 capture_output=True, text=True, timeout=600)
    first = run()
    assert first.returncode == 0, first.stderr[-3000:]
    assert "pgm_wm: compiling the loop '_same'" in first.stderr
    index = next(cache.rglob("*_same*.nbi"))
    data = next(cache.rglob("*_same*.nbc"))
    target = index if "index" in damage else data
    raw = target.read_bytes()
    target.write_bytes(raw[: len(raw) // 2] if damage.startswith("truncate") else raw[:20] + bytes(len(raw) - 20))
    second = run()
    assert second.returncode == 0, second.stderr[-3000:]
    assert "could not be loaded" in second.stderr and "rebuilding it" in second.stderr
    third = run()
    assert third.returncode == 0 and "pgm_wm:" not in third.stderr, third.stderr[-3000:]
