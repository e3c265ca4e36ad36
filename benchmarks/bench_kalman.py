"""Benchmark: pgm_wm's Kalman filter and RTS smoother side by side with the libraries a reader
would pick instead, on the same work, after checking that every contender gives our numbers.

Problem (issue 14): 256 sequences × 1000 steps of a 2-D constant-velocity model (4-d state,
2-d observed position), float64, one thread; two settings: every step observed, and 10 % of
the steps missing at random per sequence. Contenders (each optional: a missing package is
reported and skipped; install them with ``pip install -r benchmarks/requirements-bench.txt`` into
a separate environment, the book and the tests never need them):

* pgm_wm ``kalman_filter`` with ``backend="reference"`` (the book's loop), ``"fast"`` and
  ``"parallel"`` (associative scan), and ``rts_smoother`` / ``parallel_rts_smoother``;
* dynamax ``lgssm_filter`` / ``lgssm_smoother`` under ``jax.jit`` + ``jax.vmap`` (compile time
  excluded: one warm-up call), each setting with its natural input: with every step observed
  the constant ``H``; dynamax has no missing-data mask, so with missing steps (only then) a
  time-varying ``H_t`` that is ``H`` at observed steps and zero at missing ones, which leaves
  the belief unchanged exactly;
* simdkalman (NaN = missing), torch-kf (NaN = missing), statsmodels ``KalmanSmoother`` (NaN =
  missing, one sequence at a time), filterpy (``None`` = missing, one sequence at a time).

Before any timing each contender's filtered (and smoothed) means and covariances are compared
with pgm_wm's fast backend; a disagreement above 1e-6 aborts. Reported: the median over
``--repeats`` runs of the process CPU time and of the wall-clock time (filterpy and statsmodels:
one run over ``--slow-seqs`` sequences, scaled linearly). The "smoother" columns time the whole
smoothing computation from the data (filter + backward pass) for every contender.

``--scaling`` adds pgm_wm fast / parallel and dynamax over T = 1,000 … 100,000 (batch 1) and
batch 1 … 4096 (T = 1000), filter and smoother, with 1 and 2 threads, and writes figures and
JSON under ``benchmarks/results/``. ``--quick``: small sizes, one repeat (a smoke test).
Run from the repository root with the benchmark environment's python:
``PYTHONPATH=$PWD OMP_NUM_THREADS=1 /path/to/benchvenv/bin/python benchmarks/bench_kalman.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Callable

os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from pgm_wm.gaussian import Gaussian  # noqa: E402
from pgm_wm.kalman import kalman_filter, rts_smoother  # noqa: E402
from pgm_wm.kalman_parallel import parallel_rts_smoother  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def model(dt: float = 0.1, q: float = 0.5, r: float = 1.0):
    i2, z2 = np.eye(2), np.zeros((2, 2))
    F = np.block([[i2, dt * i2], [z2, i2]])
    Q = q * np.block([[dt**3 / 3 * i2, dt**2 / 2 * i2], [dt**2 / 2 * i2, dt * i2]])
    H = np.hstack([i2, z2])
    return F, H, Q, r**2 * i2, np.zeros(4), np.diag([25.0, 25.0, 1.0, 1.0])


def simulate(n_seq: int, T: int, seed: int = 0) -> np.ndarray:
    F, H, Q, R, x0, P0 = model()
    rng = np.random.default_rng(seed)
    s = rng.multivariate_normal(x0, P0, size=n_seq)
    ys = np.empty((n_seq, T, 2))
    LQ, LR = np.linalg.cholesky(Q), np.linalg.cholesky(R)
    for t in range(T):
        ys[:, t] = s @ H.T + rng.standard_normal((n_seq, 2)) @ LR.T
        s = s @ F.T + rng.standard_normal((n_seq, 4)) @ LQ.T
    return ys


# ------------------------------------------------------------------ contenders
# Each maker returns run(ys, valid, smooth) -> (means (N,T,4), covs (N,T,4,4)) as numpy, or
# raises ImportError when the package is missing.


def make_pgm(backend: str):
    F, H, Q, R, x0, P0 = (torch.as_tensor(a, dtype=torch.float64) for a in model())
    init = Gaussian(x0, P0)

    def run(ys, valid, smooth):
        y = torch.as_tensor(ys)
        mask = None if valid is None else torch.as_tensor(valid)
        res = kalman_filter(y, init, F, H, Q, R, mask, backend=backend)
        if not smooth:
            return res.posterior.mean, res.posterior.cov
        sm = parallel_rts_smoother(res, F, Q) if backend == "parallel" else rts_smoother(res, F, Q)
        return sm.mean, sm.cov
    return run


def make_dynamax():
    import jax
    import jax.numpy as jnp
    from dynamax.linear_gaussian_ssm import lgssm_filter, lgssm_smoother
    from dynamax.linear_gaussian_ssm.inference import make_lgssm_params

    F, H, Q, R, x0, P0 = (jnp.asarray(a) for a in model())

    def one(ys, H_t, smooth):
        params = make_lgssm_params(x0, P0, F, Q, H_t, R)
        if smooth:
            post = lgssm_smoother(params, ys)
            return post.smoothed_means, post.smoothed_covariances
        post = lgssm_filter(params, ys)
        return post.filtered_means, post.filtered_covariances

    # Each setting gets dynamax's natural input: every step observed -> the constant H (one
    # (2, 4) matrix); missing steps -> dynamax has no mask, so a time-varying H_t = H at observed
    # steps and 0 at missing ones (the belief is then unchanged exactly), shape (T, 2, 4).
    constant = {s: jax.jit(jax.vmap(lambda ys, s=s: one(ys, H, s))) for s in (False, True)}
    masked = {s: jax.jit(jax.vmap(lambda ys, hm, s=s: one(ys, H[None] * hm[:, None, None], s))) for s in (False, True)}
    cache: dict = {}

    def run(ys, valid, smooth):
        key = (id(ys), id(valid))
        if key not in cache:          # data transfer to JAX outside the timing
            cache.clear()
            cache[key] = (jnp.asarray(ys),) if valid is None else (
                jnp.asarray(np.where(valid[..., None], ys, 0.0)), jnp.asarray(valid.astype(float)))
        out = (constant if valid is None else masked)[smooth](*cache[key])
        jax.block_until_ready(out)
        return out
    return run


def make_simdkalman():
    import simdkalman

    F, H, Q, R, x0, P0 = model()
    kf = simdkalman.KalmanFilter(state_transition=F, process_noise=Q, observation_model=H, observation_noise=R)

    def run(ys, valid, smooth):
        data = ys if valid is None else np.where(valid[..., None], ys, np.nan)
        r = kf.compute(data, 0, initial_value=x0, initial_covariance=P0, filtered=not smooth, smoothed=smooth,
                       observations=False)
        s = r.smoothed if smooth else r.filtered
        return s.states.mean, s.states.cov
    return run


def make_torch_kf():
    from torch_kf import GaussianState, KalmanFilter

    F, H, Q, R, x0, P0 = (torch.as_tensor(a, dtype=torch.float64) for a in model())
    kf = KalmanFilter(F, H, Q, R)

    def run(ys, valid, smooth):
        data = ys if valid is None else np.where(valid[..., None], ys, np.nan)
        meas = torch.as_tensor(data).transpose(0, 1).unsqueeze(-1)                 # (T, N, 2, 1)
        N = ys.shape[0]
        state = GaussianState(x0.expand(N, 4).unsqueeze(-1).clone(), P0.expand(N, 4, 4).clone())
        out = kf.filter(state, meas, update_first=True, return_all=True)
        if smooth:
            out = kf.rts_smooth(out)
        return out.mean.squeeze(-1).transpose(0, 1), out.covariance.transpose(0, 1)
    return run


def make_statsmodels():
    from statsmodels.tsa.statespace.kalman_smoother import KalmanSmoother

    F, H, Q, R, x0, P0 = model()

    def run(ys, valid, smooth):
        means, covs = [], []
        for i in range(ys.shape[0]):
            data = ys[i] if valid is None else np.where(valid[i][:, None], ys[i], np.nan)
            ks = KalmanSmoother(k_endog=2, k_states=4, design=H, obs_cov=R, transition=F, selection=np.eye(4),
                                state_cov=Q)
            ks.bind(np.ascontiguousarray(data).T)
            ks.initialize_known(x0, P0)
            if smooth:
                r = ks.smooth()
                means.append(r.smoothed_state.T)
                covs.append(np.moveaxis(r.smoothed_state_cov, -1, 0))
            else:
                r = ks.filter()
                means.append(r.filtered_state.T)
                covs.append(np.moveaxis(r.filtered_state_cov, -1, 0))
        return np.stack(means), np.stack(covs)
    return run


def make_filterpy():
    from filterpy.kalman import KalmanFilter

    F, H, Q, R, x0, P0 = model()

    def run(ys, valid, smooth):
        means, covs = [], []
        for i in range(ys.shape[0]):
            kf = KalmanFilter(dim_x=4, dim_z=2)
            kf.F, kf.H, kf.Q, kf.R, kf.x, kf.P = F, H, Q, R, x0.copy(), P0.copy()
            zs = list(ys[i]) if valid is None else [z if v else None for z, v in zip(ys[i], valid[i])]
            m, c, _, _ = kf.batch_filter(zs, update_first=True)
            if smooth:
                m, c, _, _ = kf.rts_smoother(m, c)
            means.append(m)
            covs.append(c)
        return np.stack(means), np.stack(covs)
    return run


# name -> (maker, slow): "subset" = one run over --slow-seqs sequences scaled linearly (loops over
# sequences), "once" = one run over all sequences (batched but slow), False = median of --repeats.
CONTENDERS: dict[str, tuple[Callable, str | bool]] = {
    "pgm_wm reference": (lambda: make_pgm("reference"), "once"),
    "pgm_wm fast": (lambda: make_pgm("fast"), False),
    "pgm_wm parallel": (lambda: make_pgm("parallel"), "once"),
    "dynamax (jit+vmap)": (make_dynamax, False),
    "simdkalman": (make_simdkalman, False),
    "torch-kf": (make_torch_kf, False),
    "statsmodels": (make_statsmodels, "subset"),
    "filterpy": (make_filterpy, "subset"),
}


def as_np(x) -> np.ndarray:
    return x.detach().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def timed(fn: Callable[[], object], repeats: int) -> tuple[float, float, object]:
    """Median wall-clock and CPU seconds of ``repeats`` calls, and the last result."""
    walls, cpus, out = [], [], None
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return statistics.median(walls), statistics.median(cpus), out


def versions() -> dict[str, str]:
    from importlib import metadata

    out = {}
    for pkg in ("torch", "numpy", "jax", "dynamax", "simdkalman", "torch-kf", "statsmodels", "filterpy"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def table(args) -> dict:
    ys = simulate(args.n_seq, args.steps)
    valid = np.random.default_rng(1).random(ys.shape[:2]) >= 0.1
    ref_run = make_pgm("fast")
    rows: dict = {}
    for name, (maker, slow) in CONTENDERS.items():
        if args.only and name != "pgm_wm fast" and not any(k in name for k in args.only):
            continue
        try:
            run = maker()
        except ImportError as err:
            print(f"{name}: skipped ({err})", flush=True)
            continue
        k = min(args.slow_seqs, args.n_seq) if slow == "subset" else args.n_seq
        rows[name] = {}
        for setting, vmask in (("all observed", None), ("10% missing", valid)):
            for smooth in (False, True):
                ref = [as_np(x)[:k] for x in ref_run(ys, vmask, smooth)]
                sub = ys[:k]
                sub_mask = None if vmask is None else vmask[:k]
                got = [as_np(x) for x in run(sub, sub_mask, smooth)]                 # warm-up + check
                err = max(float(np.abs(g - r).max()) for g, r in zip(got, ref))
                if err > 1e-6:
                    raise SystemExit(f"{name} disagrees with pgm_wm ({setting}, smooth={smooth}): {err:.2e}")
                wall, cpu, _ = timed(lambda: run(sub, sub_mask, smooth), 1 if slow else args.repeats)
                scale = args.n_seq / k
                rows[name][f"{setting}|{'smoother' if smooth else 'filter'}"] = dict(
                    wall=wall * scale, cpu=cpu * scale, max_abs_diff=err, sequences_timed=k)
        print(f"{name}: done", flush=True)
    return rows


def print_table(rows: dict, args) -> str:
    cols = [f"{s}|{w}" for s in ("all observed", "10% missing") for w in ("filter", "smoother")]
    base = rows["pgm_wm fast"]
    lines = ["| contender | " + " | ".join(f"{c.replace('|', ', ')}: CPU s (ratio)" for c in cols) + " | max abs diff |",
             "|---|" + "---|" * (len(cols) + 1)]
    for name, r in rows.items():
        cells = [f"{r[c]['cpu']:.3f} ({r[c]['cpu'] / base[c]['cpu']:.2f})" for c in cols]
        approx = " ≈" if r[cols[0]]["sequences_timed"] < args.n_seq else ""
        lines.append(f"| {name}{approx} | " + " | ".join(cells) + f" | {max(r[c]['max_abs_diff'] for c in cols):.1e} |")
    text = "\n".join(lines)
    print(text)
    return text


def scaling(args) -> dict:
    """Median wall/CPU seconds over T (batch 1, 1 thread) and over the batch (T = 1000, 1 and 2
    threads), 10 % missing per sequence, filter and smoother."""
    out: dict = {}
    Ts = [1000, 10000, 100000] if not args.quick else [200, 2000]
    Ns = [1, 16, 256, 4096] if not args.quick else [1, 16]
    makers = {"pgm_wm fast": make_pgm("fast"), "pgm_wm parallel": make_pgm("parallel")}
    try:
        makers["dynamax (jit+vmap)"] = make_dynamax()
    except ImportError:
        pass
    plan = [(1, "T", Ts), (1, "batch", Ns), (2, "batch", Ns)]
    for threads, axis, grid in plan:
        torch.set_num_threads(threads)
        for v in grid:
            n_seq, T = (1, v) if axis == "T" else (v, 1000 if not args.quick else 200)
            ys = simulate(n_seq, T, seed=2)
            valid = np.random.default_rng(3).random(ys.shape[:2]) >= 0.1
            for name, run in makers.items():
                if name == "pgm_wm parallel" and n_seq * T > 300_000:
                    continue      # memory: the scan holds several (T, N, n, n) tensors
                if name.startswith("dynamax") and threads == 2:
                    continue      # XLA's thread count is fixed at start-up (1 thread)
                for smooth in (False, True):
                    if name.startswith("dynamax"):
                        run(ys, valid, smooth)                               # compile (excluded)
                    reps = 1 if n_seq * T >= 100_000 else 3
                    wall, cpu, _ = timed(lambda: run(ys, valid, smooth), reps)
                    key = f"{name}|{'smoother' if smooth else 'filter'}|threads={threads}|{axis}"
                    out.setdefault(key, []).append(dict(value=v, wall=wall, cpu=cpu))
            print(f"scaling threads={threads} {axis}={v}: done", flush=True)
    torch.set_num_threads(1)
    return out


def plot_scaling(data: dict, path: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    for axis, label in (("T", "sequence length T (batch 1)"), ("batch", "batch size (T = 1000)")):
        fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
        for ax, what in zip(axes, ("filter", "smoother")):
            for key, pts in data.items():
                name, w, thr, ax_name = key.split("|")
                if w != what or ax_name != axis:
                    continue
                ax.loglog([p["value"] for p in pts], [p["wall"] for p in pts], "o-" if "1" in thr else "s--",
                          label=f"{name}, {thr}")
            ax.set_xlabel(label)
            ax.set_title(f"{what}, 10 % missing per sequence")
            ax.grid(alpha=0.3, which="both")
        axes[0].set_ylabel("wall-clock time [s] (median)")
        axes[1].legend(fontsize=7)
        fig.tight_layout()
        f = path / f"kalman_scaling_{axis}.png"
        fig.savefig(f, dpi=110)
        plt.close(fig)
        files.append(str(f))
    return files


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n-seq", type=int, default=256)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--slow-seqs", type=int, default=16, help="sequences timed for the loop-per-sequence peers")
    ap.add_argument("--scaling", action="store_true", help="also run the scaling curves (minutes)")
    ap.add_argument("--quick", action="store_true", help="32 sequences × 200 steps, one repeat")
    ap.add_argument("--only", nargs="+", metavar="NAME", help="run only the contenders whose name contains one of "
                    "these (e.g. --only 'pgm_wm fast' dynamax); the JSON gets the suffix _only")
    args = ap.parse_args()
    if args.quick:
        args.n_seq, args.steps, args.repeats, args.slow_seqs = 32, 200, 1, 4
    torch.set_num_threads(1)
    load0 = os.getloadavg()[0]
    print(f"Kalman benchmark: {args.n_seq} sequences x {args.steps} steps, state 4, observation 2, float64, "
          f"1 thread; median of {args.repeats}; 1-min load average at start {load0:.2f} on {os.cpu_count()} CPUs",
          flush=True)
    rows = table(args)
    text = print_table(rows, args)
    report = dict(problem=dict(n_seq=args.n_seq, steps=args.steps, repeats=args.repeats, slow_seqs=args.slow_seqs),
                  versions=versions(), load_average=dict(start=load0, end=os.getloadavg()[0]), table=rows,
                  markdown=text, python=sys.version.split()[0])
    if args.scaling:
        report["scaling"] = scaling(args)
    RESULTS.mkdir(exist_ok=True)
    suffix = ("_quick" if args.quick else "") + ("_only" if args.only else "")
    if args.scaling:
        report["figures"] = plot_scaling(report["scaling"], RESULTS) if not args.quick else []
    (RESULTS / f"kalman_bench{suffix}.json").write_text(json.dumps(report, indent=1))
    print(f"written: {RESULTS / f'kalman_bench{suffix}.json'}; load average at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
