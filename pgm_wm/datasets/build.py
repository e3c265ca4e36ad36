"""Regenerate every bundled data file and ``data/SHA256SUMS`` (``python -m pgm_wm.datasets build``).

Each simulated dataset is produced by the ``generate()`` function of its module,
a pure function of the seeds and parameters stored in that module; the file
records generator name, version, seeds and parameters as JSON metadata. The Nile
CSV is written from the transcription in :mod:`pgm_wm.datasets.nile`.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Callable

import numpy as np

from . import (drift_arm, hidden_payload_arm, hysteresis_arm, memory_arm, nile, pam_arm, payload_arm, pendulum,
               slow_payload_arm, tracking)
from ._io import write_npz, write_sha256sums
from .loader import DATASET_NAMES, FILENAMES, data_dir

__all__ = ["GENERATORS", "FORMAT_VERSION", "generate_dataset", "build_all"]

FORMAT_VERSION = 1

GENERATORS: dict[str, Callable[[], tuple[dict[str, np.ndarray], dict]]] = {
    "tracking": tracking.generate,
    "pendulum": pendulum.generate,
    "hysteresis_arm": hysteresis_arm.generate,
    "payload_arm": payload_arm.generate,
    "drift_arm": drift_arm.generate,
    "memory_arm": memory_arm.generate,
    "hidden_payload_arm": hidden_payload_arm.generate,
    "slow_payload_arm": slow_payload_arm.generate,
}


def generate_dataset(name: str) -> tuple[dict[str, np.ndarray], dict]:
    """Arrays (``"<split>__<array>"`` -> float32/bool) and metadata of a simulated dataset, in memory."""
    if name not in GENERATORS:
        raise ValueError(f"name: no generator for {name!r}; valid names: {', '.join(GENERATORS)}")
    arrays, meta = GENERATORS[name]()
    meta = dict(meta)
    meta["dataset"] = name
    meta["format_version"] = FORMAT_VERSION
    meta["generator"] = {**meta["generator"],
                         "seed": {split: info["seed"] for split, info in meta["splits"].items()}}
    meta["build"] = {"numpy_version": np.__version__, "command": "python -m pgm_wm.datasets build"}
    return arrays, meta


def build_all(names: list[str] | None = None, out_dir: str | os.PathLike | None = None,
              verbose: bool = True, pam_source: str | os.PathLike | None = None) -> dict[str, dict[str, float]]:
    """Write the files of ``names`` (default: all) into ``out_dir`` and rewrite ``SHA256SUMS``.

    ``SHA256SUMS`` always lists every dataset file present in ``out_dir``. The real
    ``pam_arm`` file is converted from ``pam_source`` (default:
    :func:`pgm_wm.datasets.pam_arm.find_source`); when building everything without a
    source the committed file is kept as it is. Returns ``{name: {"seconds": ..., "bytes": ...}}``.
    """
    out = Path(out_dir) if out_dir is not None else data_dir()
    out.mkdir(parents=True, exist_ok=True)
    explicit = names is not None
    names = list(DATASET_NAMES) if names is None else list(names)
    report = {}
    for name in names:
        if name not in DATASET_NAMES:
            raise ValueError(f"names: unknown dataset {name!r}; valid names: {', '.join(DATASET_NAMES)}")
        t0 = time.perf_counter()
        path = out / FILENAMES[name]
        if name == "nile":
            nile.write_nile_csv(path)
        elif name == "pam_arm":
            source = pam_arm.find_source(pam_source)
            if source is None or not source.exists():
                if explicit:
                    raise ValueError(f"pam_source: {pam_arm.SOURCE_NAME} not found ({source}); pass "
                                     f"--pam-source or set $PGM_WM_PAM_SOURCE")
                if verbose:
                    print(f"{name:15s} kept as it is (no {pam_arm.SOURCE_NAME} found to convert)")
                continue
            arrays, meta = pam_arm.convert(source)
            meta = {**meta, "dataset": name, "format_version": FORMAT_VERSION,
                    "build": {"numpy_version": np.__version__,
                              "command": "python -m pgm_wm.datasets build --only pam_arm"}}
            write_npz(path, arrays, meta)
        else:
            arrays, meta = generate_dataset(name)
            write_npz(path, arrays, meta)
        report[name] = {"seconds": time.perf_counter() - t0, "bytes": path.stat().st_size}
        if verbose:
            print(f"{name:15s} {report[name]['bytes'] / 1e6:7.3f} MB  {report[name]['seconds']:6.2f} s  -> {path}")
    present = [FILENAMES[n] for n in DATASET_NAMES if (out / FILENAMES[n]).exists()]
    sums = write_sha256sums(out, present)
    if verbose:
        total = sum((out / f).stat().st_size for f in present)
        print(f"{'total':15s} {total / 1e6:7.3f} MB; checksums -> {sums}")
    return report
