"""Benchmark: the factorized Kalman update (Eq. rkn-update) against dense Kalman updates.

For latent state sizes L = 2m in {16, 64, 256, 1024} it times, on the same random beliefs,

* ``factorized``: :func:`pgm_wm.factorized.factorized_update` (scalar operations, O(L));
* ``dense (kf_update)``: :func:`pgm_wm.kalman.kf_update` with H = [I, 0] — Cholesky solve of the
  innovation covariance and the Joseph-form covariance update, O(L^3);
* ``dense (inverse)``: the textbook form K = Σ Hᵀ (H Σ Hᵀ + R)⁻¹, Σ⁺ = (I − K H) Σ with an
  explicit ``torch.linalg.inv`` — the cheapest dense variant, also O(L^3).

It prints the median time per call, the speed-up of the factorized update over each dense one,
and the growth exponent of each method: the least-squares slope of log(time) against log(L),
over all sizes and between the two largest sizes.
Goal from the book: at least 100x at L = 256 and O(L) growth of the factorized update. At these
sizes the factorized update is dominated by the fixed cost of launching a few dozen tensor
operations, so its slope is well below 1; the extra row with a large batch (1024 beliefs per call) shows the cost of the
arithmetic itself, which grows about linearly once it dominates the fixed cost (memory-cache
effects can push the measured exponent slightly above 1 at the largest sizes).

Run: ``python benchmarks/bench_factorized.py`` (about a minute on one CPU core).
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from typing import Callable

import torch

from pgm_wm.beliefs import DiagGaussian
from pgm_wm.factorized import FactorizedBelief, factorized_update
from pgm_wm.kalman import kf_update


def timeit(fn: Callable[[], object], min_repeats: int = 3, min_seconds: float = 0.3) -> float:
    """Median wall time of ``fn()`` over at least ``min_repeats`` calls and ``min_seconds``."""
    fn()  # warm-up
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < min_repeats or time.perf_counter() - start < min_seconds:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
        if len(times) >= 1000:
            break
    return statistics.median(times)


def random_problem(batch: int, L: int, dtype: torch.dtype, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    m = L // 2
    su = 0.5 + torch.rand(batch, m, generator=gen, dtype=dtype)
    sl = 0.5 + torch.rand(batch, m, generator=gen, dtype=dtype)
    ss = 0.5 * (su * sl).sqrt() * (2 * torch.rand(batch, m, generator=gen, dtype=dtype) - 1)
    belief = FactorizedBelief(torch.randn(batch, L, generator=gen, dtype=dtype), su, sl, ss)
    w = torch.randn(batch, m, generator=gen, dtype=dtype)
    w_var = 0.1 + torch.rand(batch, m, generator=gen, dtype=dtype)
    return belief, w, w_var


def slope(sizes: list[int], times: list[float]) -> float:
    """Least-squares slope of log(time) against log(size)."""
    x = [math.log(s) for s in sizes]
    y = [math.log(t) for t in times]
    mx, my = sum(x) / len(x), sum(y) / len(y)
    return sum((a - mx) * (b - my) for a, b in zip(x, y)) / sum((a - mx) ** 2 for a in x)


def main() -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[16, 64, 256, 1024])
    ap.add_argument("--batch", type=int, default=4, help="beliefs updated per call")
    ap.add_argument("--big-batch", type=int, default=1024, help="batch of the extra factorized row")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)

    rows = {"factorized": [], "dense (kf_update)": [], "dense (inverse)": [],
            f"factorized, batch {args.big_batch}": []}
    with torch.no_grad():
        for L in args.sizes:
            m = L // 2
            belief, w, w_var = random_problem(args.batch, L, dtype)
            dense = belief.to_dense()
            H = torch.cat([torch.eye(m, dtype=dtype), torch.zeros(m, m, dtype=dtype)], dim=-1)
            R = torch.diag_embed(w_var)
            eye = torch.eye(L, dtype=dtype)

            def textbook() -> torch.Tensor:
                PHt = dense.cov @ H.T
                K = PHt @ torch.linalg.inv(H @ PHt + R)
                mean = dense.mean + (K @ (w - dense.mean[..., :m]).unsqueeze(-1)).squeeze(-1)
                return mean, (eye - K @ H) @ dense.cov

            rows["factorized"].append(timeit(lambda: factorized_update(belief, DiagGaussian(w, w_var), validate=False)))
            rows["dense (kf_update)"].append(timeit(lambda: kf_update(dense, w, H, R)))
            rows["dense (inverse)"].append(timeit(textbook))
            big, bw, bv = random_problem(args.big_batch, L, dtype, seed=1)
            rows[f"factorized, batch {args.big_batch}"].append(
                timeit(lambda: factorized_update(big, DiagGaussian(bw, bv), validate=False)))

            # sanity check: all three agree
            post = factorized_update(belief, DiagGaussian(w, w_var))
            ref, _ = kf_update(dense, w, H, R)
            tol = 1e-3 if dtype == torch.float32 else 1e-9
            assert torch.allclose(post.to_dense().cov, ref.cov, atol=tol, rtol=tol)
            assert torch.allclose(post.to_dense().cov, textbook()[1], atol=tol, rtol=tol)

    print(f"torch {torch.__version__}, {args.threads} thread(s), {args.dtype}, batch {args.batch}")
    head = (f"{'method':<26}" + "".join(f"{'L=' + str(L):>12}" for L in args.sizes) + f"{'exponent':>10}"
            + f"{'last two':>10}")
    print(head)
    print("-" * len(head))
    for name, ts in rows.items():
        print(f"{name:<26}" + "".join(f"{t * 1e6:>10.1f}us" for t in ts) + f"{slope(args.sizes, ts):>10.2f}"
              + f"{slope(args.sizes[-2:], ts[-2:]):>10.2f}")
    print()
    print(f"{'speed-up of factorized':<26}" + "".join(f"{'L=' + str(L):>12}" for L in args.sizes))
    speedups = {}
    for name in ("dense (kf_update)", "dense (inverse)"):
        speedups[name] = [d / f for d, f in zip(rows[name], rows["factorized"])]
        print(f"{'over ' + name:<26}" + "".join(f"{s:>11.0f}x" for s in speedups[name]))
    if 256 in args.sizes:
        i = args.sizes.index(256)
        worst = min(s[i] for s in speedups.values())
        print(f"\ngoal >= 100x at L = 256: {'met' if worst >= 100 else 'NOT met'} (smallest speed-up {worst:.0f}x)")
    return {"rows": rows, "speedups": speedups}


if __name__ == "__main__":
    main()
