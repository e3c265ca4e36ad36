"""Training throughput of every chapter model, before and after a change, back to back.

One training step = draw a minibatch the way the chapter's training does (crop, imputation
mask), forward, backward, one Adam step; float32, one thread. Throughput is training sequences
per CPU second (``time.process_time``), measured after two warm-up steps (compilation and
cache loading excluded). Each version of the package runs in its own subprocess from its own
checkout (``git worktree`` of ``--before``; the working tree for ``after``), and the two
alternate ``--pairs`` times so that a change in machine load hits both. The table gives the ratio of
the medians and the ratio of the best runs (on a shared virtual machine other jobs only ever slow
a run down, so the best run is the steadier estimate of what the code can do).

    python benchmarks/bench_training.py                       # before = 8a801d6, 2 pairs
    python benchmarks/bench_training.py --models "ch4/GRU" --pairs 1 --min-cpu 2
    python benchmarks/bench_training.py --worker .            # one version, print JSON

The models and their batches are taken from the package itself (``pgm_wm.experiments``:
the chapter 4-6 studies' models and protocols; chapter 3's RKN and recurrent filters with the
notebook's sizes), through functions that exist in both versions. ``--batch`` overrides the
protocol's batch size for both versions (the comparison is always at one batch size); the
result file records it.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_BEFORE = "8a801d6"


# ----------------------------------------------------------------------------- the worker
def _steps_for(name: str, batch_override: int | None):
    """``(batch_size, step)`` for model ``name`` ("ch4/LSTM", "ch3/RKN", ...): ``step()`` runs one
    training step on a fresh minibatch."""
    import torch

    chapter, model_name = name.split("/", 1)
    gen = torch.Generator().manual_seed(0)
    if chapter == "ch3":
        from pgm_wm.builders import build_recurrent_filter, build_rkn
        from pgm_wm.datasets import load
        from pgm_wm.rnn_filters import FilterData
        from pgm_wm.training import imputation_loss_fn, random_crop, set_seed

        ds = load("pendulum", "train")
        data = FilterData.from_dataset(ds)
        shape = tuple(ds.meta["image_shape"])
        set_seed(0)
        if model_name.startswith("RKN"):
            model = build_rkn(shape, 2, 8, 15, 3, diagonal_only=model_name == "RKN, diagonal only")
            keep, gap = 0.8, 0.3
        else:
            model = build_recurrent_filter(model_name.lower(), shape, 2, 8, 15, 3)
            keep, gap = 1.0, 0.0
        loss_fn = imputation_loss_fn(model, keep, 5, "nll", gap, filtering=True)
        tensors, batch, crop = (data.obs, data.mask, data.targets), batch_override or 16, 32
    else:
        from pgm_wm.experiments.chapters import EXPERIMENTS
        from pgm_wm.training import imputation_loss_fn, random_crop

        exp = EXPERIMENTS[chapter]()
        splits, p = exp.load(), exp.protocol
        torch.manual_seed(0)
        model = exp.models[model_name].build(splits)
        obs, act, val = splits.normalized("train")
        batch = batch_override or p.batch_size
        if hasattr(model, "hip") and hasattr(model, "window") and exp.models[model_name].train is not None:
            from pgm_wm.datasets.windows import make_windows   # the HiP-RSSM's own training windows

            H = model.window
            w = make_windows(obs, act, H, val, None, model.diff_shift, model.diff_scale)
            loss_fn = imputation_loss_fn(model.hip, p.keep_prob, p.context_len - H, "nll", p.open_loop_prob)
            tensors, crop = tuple(w.tensors()), None
            model = model.hip
        else:
            loss_fn = imputation_loss_fn(model, p.keep_prob, p.context_len, "nll", p.open_loop_prob,
                                         window=p.mask_window, max_window_drop=p.max_window_drop)
            tensors, crop = (obs, act, val), p.window
    opt = torch.optim.Adam([q for q in model.parameters() if q.requires_grad], lr=1e-3)
    model.train()
    n = tensors[0].shape[0]

    def step() -> int:
        idx = torch.randint(0, n, (batch,), generator=gen) if batch > n else torch.randperm(n, generator=gen)[:batch]
        b = tuple(t[idx] for t in tensors)
        if crop is not None:
            b = random_crop(b, crop, gen)
        loss = loss_fn(b, gen)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_([q for q in model.parameters() if q.requires_grad], 5.0)
        opt.step()
        return len(idx)

    return batch, step


def all_models() -> list[str]:
    from pgm_wm.experiments.chapters import EXPERIMENTS

    names = [f"ch3/{k}" for k in ("RKN", "RKN, diagonal only", "LSTM", "GRU")]
    for chapter in ("ch4", "ch5", "ch6"):
        exp = EXPERIMENTS[chapter]()
        names += [f"{chapter}/{k}" for k, spec in exp.models.items() if spec.trained]
    return names


def worker(models: list[str] | None, min_cpu: float, batch: int | None) -> dict:
    import torch

    torch.set_num_threads(1)
    import pgm_wm

    out = {"pgm_wm": str(Path(pgm_wm.__file__).parent), "models": {}}
    for name in models or all_models():
        try:
            bs, step = _steps_for(name, batch)
        except KeyError:
            out["models"][name] = None           # this version has no such model
            continue
        step()
        step()                                  # warm-up: compilation, caches
        seqs, t0 = 0, time.process_time()
        steps = 0
        while time.process_time() - t0 < min_cpu or steps < 3:
            seqs += step()
            steps += 1
        cpu = time.process_time() - t0
        out["models"][name] = {"batch": bs, "steps": steps, "cpu_s": round(cpu, 3),
                               "seq_per_cpu_s": seqs / cpu, "ms_per_step": 1e3 * cpu / steps}
        print(f"  {name:<48} {seqs / cpu:9.1f} seq/CPU-s  ({1e3 * cpu / steps:7.1f} ms/step, batch {bs})",
              file=sys.stderr, flush=True)
    return out


# ----------------------------------------------------------------------------- the driver
def _run_worker(checkout: Path, models: list[str] | None, min_cpu: float, batch: int | None) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PGM_WM_PROGRESS="0",
               PYTHONPATH=str(checkout), PGM_WM_DATA=str(checkout / "data"))
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(checkout), "--min-cpu", str(min_cpu)]
    if models:
        cmd += ["--models", *models]
    if batch:
        cmd += ["--batch", str(batch)]
    res = subprocess.run(cmd, env=env, cwd=checkout, stdout=subprocess.PIPE, text=True, check=True)
    return json.loads(res.stdout)


def _commit(ref: str) -> str:
    return subprocess.run(["git", "rev-parse", ref], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", default=DEFAULT_BEFORE, help="git commit of the 'before' package")
    ap.add_argument("--pairs", type=int, default=2, help="before/after pairs, alternated")
    ap.add_argument("--min-cpu", type=float, default=3.0, help="CPU seconds of timed steps per model and run")
    ap.add_argument("--models", nargs="*", help='e.g. "ch4/GRU" "ch3/RKN" (default: every trained model)')
    ap.add_argument("--batch", type=int, help="one batch size for every model (default: each protocol's)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "training_throughput.json"))
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.worker:
        print(json.dumps(worker(a.models, a.min_cpu, a.batch)))
        return
    if a.pairs < 1 or a.min_cpu <= 0:
        raise SystemExit("--pairs must be >= 1 and --min-cpu > 0")
    before_commit = _commit(a.before)
    after_commit = _commit("HEAD")
    dirty = bool(subprocess.run(["git", "status", "--porcelain", "pgm_wm"], cwd=ROOT, capture_output=True,
                                text=True).stdout.strip())
    runs: dict[str, list[dict]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory() as tmp:
        before_dir = Path(tmp) / "before"
        subprocess.run(["git", "worktree", "add", "--detach", str(before_dir), before_commit], cwd=ROOT, check=True,
                       capture_output=True)
        try:
            for i in range(a.pairs):
                for label, checkout in (("before", before_dir), ("after", ROOT)):
                    print(f"pair {i + 1}/{a.pairs}: {label}", file=sys.stderr, flush=True)
                    runs[label].append(_run_worker(checkout, a.models, a.min_cpu, a.batch))
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(before_dir)], cwd=ROOT, capture_output=True)
    names = list(runs["after"][0]["models"])
    table = {}
    for name in names:
        b = [r["models"].get(name) for r in runs["before"]]
        f = [r["models"].get(name) for r in runs["after"]]
        med = lambda xs: None if any(x is None for x in xs) else statistics.median(x["seq_per_cpu_s"] for x in xs)  # noqa: E731
        best = lambda xs: None if any(x is None for x in xs) else max(x["seq_per_cpu_s"] for x in xs)  # noqa: E731
        mb, mf, bb, bf = med(b), med(f), best(b), best(f)
        table[name] = {"batch": f[0]["batch"] if f[0] else None, "before_seq_per_cpu_s": mb, "after_seq_per_cpu_s": mf,
                       "ratio": None if not (mb and mf) else mf / mb,
                       "ratio_of_best": None if not (bb and bf) else bf / bb,
                       "before_runs": [x and round(x["seq_per_cpu_s"], 2) for x in b],
                       "after_runs": [x and round(x["seq_per_cpu_s"], 2) for x in f]}
    for label, expected in (("before", "before"), ("after", str(ROOT / "pgm_wm"))):
        got = runs[label][0]["pgm_wm"]
        if (label == "before") == got.startswith(str(ROOT)):
            raise SystemExit(f"the {label} worker imported pgm_wm from {got}: the versions got mixed up")
    result = {"before_commit": before_commit, "after_commit": after_commit, "after_tree_dirty": dirty,
              "pairs": a.pairs, "min_cpu_s": a.min_cpu, "batch_override": a.batch, "threads": 1, "dtype": "float32",
              "load_avg_at_end": os.getloadavg(), "date": time.strftime("%Y-%m-%d %H:%M"), "models": table}
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(result, indent=1) + "\n")
    print(f"\n{'model':<48} {'before':>9} {'after':>9} {'ratio':>7} {'best/best':>9}")
    for name, row in table.items():
        fmt = lambda v: "   n/a" if v is None else f"{v:9.1f}"  # noqa: E731
        rfmt = lambda v: "    n/a" if v is None else f"{v:6.2f}x"  # noqa: E731
        print(f"{name:<48} {fmt(row['before_seq_per_cpu_s'])} {fmt(row['after_seq_per_cpu_s'])} {rfmt(row['ratio'])} "
              f"{rfmt(row['ratio_of_best']):>9}")
    print(f"written to {a.out}")


if __name__ == "__main__":
    main()
