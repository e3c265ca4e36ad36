"""Benchmark: pgm_wm's batched Kalman filter vs filterpy looping over sequences.

256 sequences × 1000 steps, 4-d state (2-D constant-velocity model), 2-d observation,
float64, one thread. Both filters compute the filtered means and covariances of every step;
ours also returns the per-step log-likelihoods (filterpy's ``batch_filter`` does not). Two
settings:

* ``all observed``  — no mask. With unbatched parameters the covariance recursion does not
  depend on the data, so our filter computes it once for the whole batch (exact, not an
  approximation); filterpy recomputes it for every sequence.
* ``10% missing``   — a random per-sequence mask, so every sequence has its own covariances
  and our filter carries a batch of 256 covariance matrices through the loop.

filterpy runs once over all sequences (it takes seconds); ours is the best of ``--repeats``
runs. Both wall-clock time and process CPU time are reported: on a shared machine the CPU time
is the steadier of the two, because other processes inflate the wall-clock time of both
contenders. The two filters' outputs are checked against each other (max abs. difference
< 1e-8) before the timings are printed. Run: ``python benchmarks/bench_kalman.py``
(``--quick`` for a smoke test).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch
from filterpy.kalman import KalmanFilter

from pgm_wm.gaussian import Gaussian
from pgm_wm.kalman import kalman_filter


def model(dt: float = 0.1, q: float = 0.5, r: float = 1.0):
    i2, z2 = np.eye(2), np.zeros((2, 2))
    F = np.block([[i2, dt * i2], [z2, i2]])
    Q = q * np.block([[dt**3 / 3 * i2, dt**2 / 2 * i2], [dt**2 / 2 * i2, dt * i2]])
    H = np.hstack([i2, z2])
    R = r**2 * i2
    return F, H, Q, R, np.zeros(4), np.diag([25.0, 25.0, 1.0, 1.0])


def simulate(n_seq: int, T: int, seed: int = 0):
    F, H, Q, R, x0, P0 = model()
    rng = np.random.default_rng(seed)
    s = rng.multivariate_normal(x0, P0, size=n_seq)
    ys = np.empty((n_seq, T, 2))
    for t in range(T):
        ys[:, t] = s @ H.T + rng.multivariate_normal(np.zeros(2), R, size=n_seq)
        s = s @ F.T + rng.multivariate_normal(np.zeros(4), Q, size=n_seq)
    return ys


def run_filterpy(ys: np.ndarray, valid: np.ndarray | None):
    F, H, Q, R, x0, P0 = model()
    means, covs = [], []
    for i in range(ys.shape[0]):
        kf = KalmanFilter(dim_x=4, dim_z=2)
        kf.F, kf.H, kf.Q, kf.R, kf.x, kf.P = F, H, Q, R, x0.copy(), P0.copy()
        zs = list(ys[i]) if valid is None else [z if v else None for z, v in zip(ys[i], valid[i])]
        m, c, _, _ = kf.batch_filter(zs, update_first=True)
        means.append(m)
        covs.append(c)
    return np.stack(means), np.stack(covs)


def run_ours(y: torch.Tensor, mask: torch.Tensor | None, params):
    F, H, Q, R, init = params
    return kalman_filter(y, init, F, H, Q, R, mask=mask)


def timed(fn) -> tuple[float, float, object]:
    """(wall seconds, CPU seconds, result) of one call."""
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return time.perf_counter() - w0, time.process_time() - c0, out


def best_of(fn, repeats: int) -> tuple[float, float, object]:
    runs = [timed(fn) for _ in range(repeats)]
    return min(r[0] for r in runs), min(r[1] for r in runs), runs[-1][2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-seq", type=int, default=256)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--filterpy-seqs", type=int, default=None,
                    help="time filterpy on this many sequences and scale to n-seq (default: all)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="64 sequences × 200 steps, one repeat")
    args = ap.parse_args()
    if args.quick:
        args.n_seq, args.steps, args.filterpy_seqs, args.repeats = 64, 200, 16, 1
    torch.set_num_threads(1)

    ys = simulate(args.n_seq, args.steps)
    valid = np.random.default_rng(1).random(ys.shape[:2]) >= 0.1
    F, H, Q, R, x0, P0 = (torch.as_tensor(a, dtype=torch.float64) for a in model())
    params = (F, H, Q, R, Gaussian(x0, P0))
    y = torch.as_tensor(ys)
    k = args.n_seq if args.filterpy_seqs is None else min(args.filterpy_seqs, args.n_seq)
    scale = args.n_seq / k

    print(f"Kalman filter benchmark: {args.n_seq} sequences x {args.steps} steps, state 4, "
          f"observation 2, float64, torch threads = {torch.get_num_threads()}")
    print(f"filterpy: one run over {k} sequences" + (f", scaled by {scale:g}" if k != args.n_seq else "")
          + f"; pgm_wm: best of {args.repeats}")
    rows = []
    for name, vmask in (("all observed", None), ("10% missing", valid)):
        mask = None if vmask is None else torch.as_tensor(vmask)
        w_fp, c_fp, (m_fp, c_fp_out) = timed(lambda: run_filterpy(ys[:k], None if vmask is None else vmask[:k]))
        w_fp, c_fp = w_fp * scale, c_fp * scale
        w_us, c_us, res = best_of(lambda: run_ours(y, mask, params), args.repeats)
        err = max(
            float(np.abs(res.filtered.mean[:k].numpy() - m_fp).max()),
            float(np.abs(res.filtered.cov[:k].numpy() - c_fp_out).max()),
        )
        assert err < 1e-8, f"filters disagree: max abs difference {err:.2e}"
        rows.append((name, w_fp, w_us, c_fp, c_us, err))

    print(f"{'':<14} {'wall-clock time [s]':^32} {'CPU time [s]':^32}")
    print(f"{'setting':<14} {'filterpy':>9} {'pgm_wm':>9} {'ratio':>12} {'filterpy':>9} {'pgm_wm':>9} {'ratio':>12}"
          f" {'max |diff|':>11}")
    for name, w_fp, w_us, c_fp, c_us, err in rows:
        print(f"{name:<14} {w_fp:>9.3f} {w_us:>9.3f} {w_fp / w_us:>11.1f}x {c_fp:>9.3f} {c_us:>9.3f}"
              f" {c_fp / c_us:>11.1f}x {err:>11.1e}")
    if os.cpu_count():
        print(f"(machine: {os.cpu_count()} logical CPUs; 1-minute load average at the end: "
              f"{os.getloadavg()[0]:.2f})")


if __name__ == "__main__":
    main()
