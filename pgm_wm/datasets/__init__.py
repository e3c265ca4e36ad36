"""Bundled datasets for the book: small, seeded, offline stand-ins for the thesis' robot logs.

>>> from pgm_wm.datasets import load
>>> data = load("hysteresis_arm", "train")      # doctest: +SKIP
>>> data.obs.shape, data.actions.shape           # (n, T, 2), (n, T, 2)  # doctest: +SKIP

Datasets (see ``data/README.md`` for equations, sizes and provenance):

- ``nile`` (ch. 1): the real Nile flow series 1871-1970, ``obs (1, 100, 1)``;
- ``tracking`` (ch. 1): 2-D constant-velocity target, noisy positions, some missing;
- ``pendulum`` (ch. 3): 24x24 images of a damped stochastic pendulum with
  random-walk corruption, rendered at load time by :func:`render_pendulum`;
- ``hysteresis_arm`` (ch. 4): pneumatic-muscle-like joints, angles only, non-Markov;
- ``payload_arm`` (ch. 2, 5): PD-controlled 2-link arm with a tip payload, held-out
  interpolation/extrapolation payloads and switching payloads;
- ``drift_arm`` (ch. 6): the same arm over 40 s episodes with a slowly drifting payload;
- ``memory_arm`` (ch. 4): long-memory hysteresis (play operators + creep), angles only;
- ``hidden_payload_arm`` (ch. 5): horizontal arm whose payload acts only through inertia;
- ``slow_payload_arm`` (ch. 6): angles only, a pump action fills a tank payload slowly;
- ``pam_arm`` (ch. 4): real pneumatic-muscle arm, 616 episodes (MIT, Shaj et al. 2020).

Physics oracles for the results tables: :func:`oracle_windows` predicts the evaluation
windows of a simulated arm with the true simulator from the true state, with the true or the
nominal payload (:mod:`pgm_wm.datasets.oracles`).

Every file is checked against ``data/SHA256SUMS`` before use (:class:`DataFileError`).

Your own data: ``SequenceData.from_arrays(obs, actions, valid)`` checks and wraps
numpy arrays or tensors, :func:`split_sequences` splits them by sequence into a named tuple
``(train, valid, test)`` (seeded, statistics of the training part) and :func:`compute_stats` gives masked statistics.

Regenerate every file with ``python -m pgm_wm.datasets build``.
"""

from ._io import DataFileError
from .loader import ACTION_OPTIONS, DATASET_NAMES, SPLITS, SequenceData, data_dir, load
from .oracles import oracle_windows
from .pendulum import render_pendulum
from .sequences import SequenceSplits, compute_stats, split_sequences

__all__ = ["load", "SequenceData", "SequenceSplits", "compute_stats", "split_sequences", "DATASET_NAMES", "SPLITS", "ACTION_OPTIONS", "render_pendulum", "data_dir",
           "DataFileError", "oracle_windows"]
