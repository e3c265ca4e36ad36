"""Benchmark: training throughput of Chapter 6's MTS3 (issue 14), in sequences per second.

What is timed is one optimizer step of the notebook's training, exactly as ``fit`` runs it
(``notebooks/06_mts3.ipynb``): ``build_mts3(obs_dim, action_dim, 8, H, (32,))`` on the
``slow_payload_arm`` training split, batches of 48 random crops of 100 steps, the notebook's
two-scale imputation loss (``imputation_loss_fn(model, 0.85, 25, open_loop_prob=0.5, window=25,
max_window_drop=0.75, open_loop_start=25)``), forward + backward + Adam step, float32, one thread.
Reported per window ``H`` (the notebook trains H = 10, 25 and 50): the median over ``--repeats``
blocks of ``--steps`` optimizer steps of the process CPU time per step, turned into sequences per
second (48 / CPU s per step), after ``--warmup`` untimed steps.

``--label before|after`` stores the run under that key in
``benchmarks/results/ch6_training_throughput.json`` (other keys are kept), with the commit of the
imported ``pgm_wm``, the machine and the load average. Run from the repository root:
``PYTHONPATH=$PWD OMP_NUM_THREADS=1 python benchmarks/bench_ch6_training.py --label after``; for
``before``, point ``PYTHONPATH`` at a checkout of the older commit (``git worktree add``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import torch

from pgm_wm.datasets import load
from pgm_wm.mts3 import build_mts3
from pgm_wm.training import imputation_loss_fn, random_crop, set_seed

RESULTS = Path(__file__).resolve().parent / "results" / "ch6_training_throughput.json"
BATCH, CROP, M_LAT, HID, MASK_WINDOW = 48, 100, 8, (32,), 25


def commit() -> str:
    """The commit of the ``pgm_wm`` that is imported (the code being timed; ``PYTHONPATH`` may
    point at another checkout than this script's), ``+dirty`` with uncommitted tracked changes."""
    import pgm_wm

    where = Path(pgm_wm.__file__).resolve().parent
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True, cwd=where)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, cwd=where).stdout.strip()
        return out.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def throughput(H: int, steps: int, repeats: int, warmup: int) -> dict:
    train = load("slow_payload_arm", "train")
    obs, act = train.normalize_obs(train.obs), train.normalize_actions(train.actions)
    set_seed(0)
    model = build_mts3(train.obs_dim, train.action_dim, M_LAT, H, HID)
    loss_fn = imputation_loss_fn(model, 0.85, MASK_WINDOW, open_loop_prob=0.5, window=MASK_WINDOW,
                                 max_window_drop=0.75, open_loop_start=MASK_WINDOW)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    gen = torch.Generator().manual_seed(0)

    def step() -> None:
        idx = torch.randint(0, obs.shape[0], (BATCH,), generator=gen)
        batch = random_crop((obs[idx], act[idx]), CROP, gen)
        loss = loss_fn(batch, gen)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    for _ in range(warmup):
        step()
    cpu, wall = [], []
    for _ in range(repeats):
        c0, w0 = time.process_time(), time.perf_counter()
        for _ in range(steps):
            step()
        cpu.append((time.process_time() - c0) / steps)
        wall.append((time.perf_counter() - w0) / steps)
    c, w = statistics.median(cpu), statistics.median(wall)
    return dict(cpu_s_per_step=c, wall_s_per_step=w, sequences_per_cpu_s=BATCH / c, sequences_per_wall_s=BATCH / w)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--label", default="latest", help="key of this run in the JSON (e.g. before, after)")
    ap.add_argument("--windows", type=int, nargs="+", default=[10, 25, 50])
    ap.add_argument("--steps", type=int, default=10, help="optimizer steps per timed block")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--no-save", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(1)
    load0 = os.getloadavg()[0]
    rows = {}
    for H in args.windows:
        rows[f"H={H}"] = r = throughput(H, args.steps, args.repeats, args.warmup)
        print(f"H={H}: {r['cpu_s_per_step'] * 1e3:.1f} ms CPU per step, {r['sequences_per_cpu_s']:.0f} sequences "
              f"per CPU s ({r['sequences_per_wall_s']:.0f} per wall s)", flush=True)
    run = dict(commit=commit(), date=datetime.now(timezone.utc).isoformat(timespec="seconds"),
               machine=dict(platform=platform.platform(), processor=platform.processor() or platform.machine(),
                            cpus=os.cpu_count(), torch=torch.__version__, python=sys.version.split()[0]),
               load_average=dict(start=load0, end=os.getloadavg()[0]),
               problem=dict(batch=BATCH, crop=CROP, latent_obs_dim=M_LAT, hidden=list(HID), dtype="float32",
                            threads=1, steps=args.steps, repeats=args.repeats, warmup=args.warmup),
               results=rows)
    if not args.no_save:
        data = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
        data[args.label] = run
        if "before" in data and "after" in data:
            data["speedup_cpu"] = {k: data["before"]["results"][k]["cpu_s_per_step"]
                                   / data["after"]["results"][k]["cpu_s_per_step"]
                                   for k in data["after"]["results"] if k in data["before"]["results"]}
        RESULTS.parent.mkdir(exist_ok=True)
        RESULTS.write_text(json.dumps(data, indent=1))
        print(f"written: {RESULTS} ({args.label}); load average {load0:.2f} -> {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
