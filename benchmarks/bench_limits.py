"""What bounds the training throughput of the chapter models now (issue 20), measured.

``bench_training.py`` compares two versions of the package; this script asks of the current one
where the rest of a training step goes, and whether a larger batch would help, in three
measurements (float32, one thread, CPU seconds of ``time.process_time``, after two warm-up calls):

1. **The Chapter 3 RKN's image encoder.** A training step of the RKN (batch 16 crops of 32 frames
   of 24 x 24 pixels) against the encoder's forward and backward pass alone on the same 512
   frames. The encoder is the same at every commit, so ``before_step_ms / encoder_ms`` is the
   largest ratio any change to the rest of the model could reach (the ``before`` step is timed in
   a subprocess on a temporary ``git worktree`` of 8a801d6, the code before issue 20, with the
   same batch, on the same machine).
2. **The compiled locally linear filter** of Chapters 3-5 (``pgm_wm._backends.locally_linear_jit``)
   at the Chapter 4 ac-RKN's sizes (m = 15, 15 basis matrices, bandwidth 3, 128 sequences of 50
   steps): forward alone, forward + backward.
3. **Throughput against batch size** for the models whose gain fell short: sequences per CPU
   second at the protocol's batch and at four times it. A model bound by dispatching small
   operations gains from the larger batch; one bound by arithmetic or memory traffic does not.

    PYTHONPATH=$PWD OMP_NUM_THREADS=1 python benchmarks/bench_limits.py          # 1-2 min
    PYTHONPATH=$PWD OMP_NUM_THREADS=1 python benchmarks/bench_limits.py --no-save

Writes ``results/throughput_limits.json`` with the commit, the machine's load average and the
date.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_training import DEFAULT_BEFORE, _run_worker, worker  # noqa: E402  (the throughput benchmark's step and timing)

BATCH_MODELS = ("ch3/RKN", "ch6/GRU", "ch6/LSTM", "ch6/Transformer", "ch6/MTS3 (H = 25)",
                "ch4/ac-RKN (difference readout)")


def cpu_ms(fn, min_cpu: float = 2.0, min_calls: int = 5) -> float:
    """CPU milliseconds per call of ``fn`` (at least ``min_cpu`` s and ``min_calls`` calls, after two warm-up
    calls), for the parts of a step that ``bench_training.worker`` cannot time on their own."""
    fn()
    fn()
    calls, t0 = 0, time.process_time()
    while time.process_time() - t0 < min_cpu or calls < min_calls:
        fn()
        calls += 1
    return 1e3 * (time.process_time() - t0) / calls


def encoder_bound(min_cpu: float) -> dict:
    from pgm_wm.builders import build_image_encoder
    from pgm_wm.datasets import load

    after = worker(["ch3/RKN"], min_cpu, None)["models"]["ch3/RKN"]   # timed as bench_training times it
    batch, step_ms = after["batch"], after["ms_per_step"]
    shape = tuple(load("pendulum", "train").meta["image_shape"])        # 24 x 24
    torch.manual_seed(0)
    enc = build_image_encoder(shape, 8)                                 # bench_training's RKN: latent 8, crops of 32
    frames = torch.rand(batch, 32, shape[0] * shape[1])

    def fwd_bwd() -> None:
        w, v = enc(frames)
        (w.sum() + v.sum()).backward()

    enc_ms = cpu_ms(fwd_bwd, min_cpu)
    with tempfile.TemporaryDirectory() as tmp:      # the same step at the code before issue 20, on this machine
        before_dir = Path(tmp) / "before"
        subprocess.run(["git", "worktree", "add", "--detach", str(before_dir), DEFAULT_BEFORE], cwd=ROOT, check=True,
                       capture_output=True)
        try:
            row = _run_worker(before_dir, ["ch3/RKN"], min_cpu, None)["models"]["ch3/RKN"]
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(before_dir)], cwd=ROOT, capture_output=True)
    before_ms = row["ms_per_step"]
    return {"batch": batch, "frames_per_step": batch * 32, "step_ms": step_ms, "encoder_fwd_bwd_ms": enc_ms,
            "encoder_share_of_step": enc_ms / step_ms, "before_commit": DEFAULT_BEFORE, "before_step_ms": before_ms,
            "largest_ratio_without_changing_the_encoder": before_ms / enc_ms,
            "step_ms_needed_for_10x": before_ms / 10}


def filter_forward_backward(min_cpu: float) -> dict:
    from pgm_wm._backends.locally_linear_jit import band_pairs, locally_linear_filter_jit

    m, K, bandwidth, N, T = 15, 15, 3, 128, 50
    bi, bj = band_pairs(m, bandwidth)
    nb = len(bi)
    torch.manual_seed(0)
    x0 = torch.rand(5 * m, N)
    x0[2 * m:] += 1.0
    x0[3 * m:4 * m] = 0.1
    w = torch.randn(T, m, N, requires_grad=True)
    r = (torch.rand(T, m, N) + 0.5).requires_grad_()
    inp = (0.01 * torch.rand(T, 5 * m, N)).requires_grad_()
    basis = (0.05 * torch.randn(4, K, nb)).requires_grad_()
    Wc, bc = (0.1 * torch.randn(K, 2 * m)).requires_grad_(), torch.zeros(K, requires_grad=True)
    ident = (torch.as_tensor(bi) == torch.as_tensor(bj)).float()
    mu = (torch.rand(T, N) < 0.8).float()

    def forward() -> None:
        with torch.no_grad():
            locally_linear_filter_jit(x0, w, r, mu, inp, basis, Wc, bc, ident, bi, bj)

    def forward_backward() -> None:
        X, P = locally_linear_filter_jit(x0, w, r, mu, inp, basis, Wc, bc, ident, bi, bj)
        (X.sum() + P.sum()).backward()

    f, fb = cpu_ms(forward, min_cpu), cpu_ms(forward_backward, min_cpu)
    return {"sizes": {"m": m, "basis": K, "bandwidth": bandwidth, "sequences": N, "steps": T},
            "forward_ms": f, "forward_backward_ms": fb, "backward_ms": fb - f, "backward_over_forward": (fb - f) / f}


def batch_scaling(models: tuple[str, ...], min_cpu: float) -> dict:
    out = {}
    for name in models:
        runs = [worker([name], min_cpu, None)["models"][name]]           # the protocol's batch, then four times it
        base = runs[0]["batch"]
        runs.append(worker([name], min_cpu, 4 * base)["models"][name])
        row = {str(r["batch"]): {"ms_per_step": r["ms_per_step"], "seq_per_cpu_s": r["seq_per_cpu_s"]} for r in runs}
        row["ratio_4x_batch"] = row[str(4 * base)]["seq_per_cpu_s"] / row[str(base)]["seq_per_cpu_s"]
        out[name] = row
        print(f"  {name:<40} batch {base}: {row[str(base)]['seq_per_cpu_s']:7.0f} seq/CPU-s, batch {4 * base}: "
              f"{row[str(4 * base)]['seq_per_cpu_s']:7.0f} ({row['ratio_4x_batch']:.2f}x)", file=sys.stderr, flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--min-cpu", type=float, default=3.0, help="CPU seconds of timed calls per measurement")
    ap.add_argument("--models", nargs="*", default=list(BATCH_MODELS), help="models of the batch measurement")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "throughput_limits.json"))
    ap.add_argument("--no-save", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(1)
    load0 = os.getloadavg()
    res = {"encoder_bound": encoder_bound(a.min_cpu)}
    print(json.dumps(res["encoder_bound"], indent=1), file=sys.stderr)
    res["locally_linear_filter"] = filter_forward_backward(a.min_cpu)
    print(json.dumps(res["locally_linear_filter"], indent=1), file=sys.stderr)
    res["batch_scaling"] = batch_scaling(tuple(a.models), a.min_cpu)
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    dirty = bool(subprocess.run(["git", "status", "--porcelain", "pgm_wm"], cwd=ROOT, capture_output=True,
                                text=True).stdout.strip())
    res.update(commit=commit, pgm_wm_dirty=dirty, threads=1, dtype="float32", load_avg_at_start=load0,
               load_avg_at_end=os.getloadavg(), date=time.strftime("%Y-%m-%d %H:%M"))
    if not a.no_save:
        Path(a.out).write_text(json.dumps(res, indent=1) + "\n")
        print(f"written to {a.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
