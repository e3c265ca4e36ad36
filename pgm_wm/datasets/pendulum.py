r"""Damped stochastic pendulum seen through corrupted 24x24 images (chapter 3, RKN).

Dynamics (angle :math:`\theta` from the downward vertical, rad; :math:`\omega = \dot\theta`):

.. math::

    d\theta = \omega\, dt,\qquad
    d\omega = \left(-\frac{g}{l}\sin\theta - \gamma\,\omega\right) dt + \sigma\, dW_t,

integrated with semi-implicit Euler-Maruyama on ``n_substeps`` substeps of
:math:`h = \Delta / n_\text{sub}` per frame:
:math:`\omega \leftarrow \omega + h(-\tfrac{g}{l}\sin\theta - \gamma\omega) + \sigma\sqrt{h}\,\epsilon`,
:math:`\theta \leftarrow \theta + h\,\omega`. Initial state
:math:`\theta_0 \sim U(-\pi, \pi)`, :math:`\omega_0 \sim U(-\omega_\max, \omega_\max)`.

Corruption (per sequence, as in the RKN paper's noisy pendulum): a noise
factor :math:`f_t \in [0, 1]` follows a clipped random walk,
:math:`f_0 \sim U(0, 1)`, :math:`f_{t+1} = \operatorname{clip}(f_t + \sigma_f \epsilon_t, 0, 1)`,
with the first ``n_clean`` frames forced clean (:math:`f_t = 1`). The observed image is

.. math::

    o_t = f_t\, I(\theta_t) + (1 - f_t)\, U_t,\qquad U_t \sim \text{Uniform}(0, 1)^{24\times 24},

where :math:`I(\theta)` is the anti-aliased drawing of the rod and bob
(:func:`render_pendulum`). After the clean frames, each frame is missing with
probability ``p_missing``. Only the states, factors and masks are stored; the
images are rendered at load time with a seeded noise stream.
"""

from __future__ import annotations

import functools

import numpy as np

__all__ = [
    "VERSION",
    "DEFAULT_PARAMS",
    "SPLITS",
    "IMAGE_SIZE",
    "simulate_pendulum",
    "render_pendulum",
    "generate",
]

VERSION = "1.0"
IMAGE_SIZE = 24

DEFAULT_PARAMS: dict = {
    "dt": 0.05,          # s per frame
    "n_substeps": 10,
    "g": 9.81,           # m/s^2
    "length": 1.0,       # m
    "damping": 0.25,     # 1/s
    "sigma": 0.5,        # rad / s^(3/2), process noise on the angular velocity
    "omega_max": 2.0,    # rad/s, initial velocity range
    "sigma_f": 0.2,      # random-walk step of the noise factor
    "n_clean": 5,        # first frames are never corrupted or missing
    "p_missing": 0.1,
}

# split -> (n_sequences, T, simulation seed, render seed)
SPLITS: dict[str, tuple[int, int, int, int]] = {
    "train": (256, 100, 3101, 3201),
    "valid": (64, 100, 3102, 3202),
    "test": (128, 100, 3103, 3203),
}

# Drawing geometry in pixels (pivot at the image centre, theta = 0 hangs down).
_ROD_LENGTH_PX = 8.5
_ROD_HALF_WIDTH = 0.9
_BOB_RADIUS = 2.2


def simulate_pendulum(seed: int, n: int, T: int, params: dict | None = None) -> dict[str, np.ndarray]:
    """Simulate ``n`` sequences of ``T`` frames; pure function of its arguments.

    Returns float64/bool arrays ``angle (n, T)``, ``velocity (n, T)``,
    ``noise_factor (n, T)`` and ``valid (n, T)``.
    """
    p = {**DEFAULT_PARAMS, **(params or {})}
    rng = np.random.default_rng(seed)
    k = int(p["n_substeps"])
    h = p["dt"] / k
    theta = rng.uniform(-np.pi, np.pi, size=n)
    omega = rng.uniform(-p["omega_max"], p["omega_max"], size=n)
    eps = rng.standard_normal((T, k, n))
    angle = np.empty((n, T))
    velocity = np.empty((n, T))
    for t in range(T):
        angle[:, t] = theta
        velocity[:, t] = omega
        for j in range(k):
            omega = omega + h * (-(p["g"] / p["length"]) * np.sin(theta) - p["damping"] * omega) \
                + p["sigma"] * np.sqrt(h) * eps[t, j]
            theta = theta + h * omega
    f = np.empty((n, T))
    f[:, 0] = rng.uniform(0.0, 1.0, size=n)
    steps = p["sigma_f"] * rng.standard_normal((n, T))
    for t in range(1, T):
        f[:, t] = np.clip(f[:, t - 1] + steps[:, t], 0.0, 1.0)
    n_clean = int(p["n_clean"])
    f[:, :n_clean] = 1.0
    valid = rng.random((n, T)) >= p["p_missing"]
    valid[:, :n_clean] = True
    return {"angle": angle, "velocity": velocity, "noise_factor": f, "valid": valid}


_N_BINS = 4096  # angles are rounded to multiples of 2 pi / 4096 before drawing


def _clean_images(angles: np.ndarray, size: int) -> np.ndarray:
    """Noise-free images ``(m, size, size)`` float32 for ``angles (m,)``; see :func:`render_pendulum`."""
    scale = size / IMAGE_SIZE
    c = (size - 1) / 2.0
    coords = np.arange(size, dtype=np.float32) - np.float32(c)
    rows = coords[:, None]  # downward offset of each pixel centre from the pivot
    cols = coords[None, :]
    ux = np.sin(angles).astype(np.float32)[:, None, None]   # rod direction, column axis
    uy = np.cos(angles).astype(np.float32)[:, None, None]   # rod direction, row axis
    L = np.float32(_ROD_LENGTH_PX * scale)
    along = cols * ux + rows * uy                               # projection on the rod axis
    across2 = (cols * cols + rows * rows) - along * along       # squared distance to the axis line
    beyond = np.clip(along, 0.0, L) - along                     # offset past the segment's ends
    d_rod = np.sqrt(np.maximum(across2, 0.0) + beyond * beyond)
    d_bob = np.sqrt((cols - L * ux) ** 2 + (rows - L * uy) ** 2)
    return np.maximum(
        np.clip(np.float32(_ROD_HALF_WIDTH * scale + 0.5) - d_rod, 0.0, 1.0),
        np.clip(np.float32(_BOB_RADIUS * scale + 0.5) - d_bob, 0.0, 1.0),
    )


@functools.lru_cache(maxsize=4)
def _clean_table(size: int) -> np.ndarray:
    """Clean images ``(4096, size*size)`` for the angles ``2 pi k / 4096`` (computed once)."""
    grid = 2.0 * np.pi * np.arange(_N_BINS) / _N_BINS
    table = _clean_images(grid, size).reshape(_N_BINS, size * size)
    table.setflags(write=False)
    return table


def render_pendulum(
    angles: np.ndarray, noise_factors: np.ndarray, seed: int, size: int = IMAGE_SIZE
) -> np.ndarray:
    r"""Render corrupted pendulum images, flattened: ``angles (...)`` -> ``(..., size*size)`` float32.

    Clean image :math:`I(\theta)`: each pixel's intensity is
    :math:`\max(\operatorname{clip}(w + \tfrac12 - d_\text{rod}, 0, 1),\ \operatorname{clip}(r + \tfrac12 - d_\text{bob}, 0, 1))`
    with :math:`d_\text{rod}` the distance from the pixel centre to the rod
    segment (pivot at the centre, length 8.5 px, :math:`\theta = 0` pointing
    down) and :math:`d_\text{bob}` the distance to the rod's end (bob radius
    2.2 px, rod half-width 0.9 px). Angles are rounded to the nearest multiple of
    :math:`2\pi/4096` (at most 0.007 px at the rod's end) so that clean images
    come from a precomputed table. Corrupted image: :math:`f I(\theta) + (1 - f) U`,
    ``U`` uniform noise drawn from ``numpy.random.default_rng(seed)`` in one block
    of shape ``(..., size * size)``, so the same inputs and seed always give the
    same images. Pixels lie in [0, 1];
    row index grows downwards, pixel ``(i, j)`` is element ``i * size + j``.
    """
    angles = np.asarray(angles, dtype=np.float64)
    noise_factors = np.asarray(noise_factors, dtype=np.float64)
    if angles.shape != noise_factors.shape:
        raise ValueError(
            f"noise_factors: expected the shape of angles {angles.shape}, got {noise_factors.shape}"
        )
    if noise_factors.size and (noise_factors.min() < 0 or noise_factors.max() > 1):
        raise ValueError("noise_factors: must lie in [0, 1]")
    if not np.isfinite(angles).all():
        raise ValueError("angles: contains NaN or infinite values")
    if not isinstance(size, (int, np.integer)) or size < 8:
        raise ValueError(f"size: expected an integer >= 8, got {size!r}")
    size = int(size)
    bins = np.rint(np.mod(angles.reshape(-1), 2.0 * np.pi) * (_N_BINS / (2.0 * np.pi))).astype(np.int64) % _N_BINS
    f = noise_factors.reshape(-1, 1).astype(np.float32)
    out = np.random.default_rng(seed).random((bins.size, size * size), dtype=np.float32)
    out *= np.float32(1.0) - f
    clean = _clean_table(size)[bins]
    clean *= f
    out += clean
    return out.reshape(angles.shape + (size * size,))


def generate(params: dict | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """All splits as ``({"<split>__<array>": array}, meta)``; images are *not* stored."""
    p = {**DEFAULT_PARAMS, **(params or {})}
    arrays: dict[str, np.ndarray] = {}
    splits_meta = {}
    for split, (n, T, seed, render_seed) in SPLITS.items():
        out = simulate_pendulum(seed, n, T, p)
        arrays[f"{split}__hidden__angle"] = out["angle"].astype(np.float32)
        arrays[f"{split}__hidden__velocity"] = out["velocity"].astype(np.float32)
        arrays[f"{split}__hidden__noise_factor"] = out["noise_factor"].astype(np.float32)
        arrays[f"{split}__valid"] = out["valid"]
        splits_meta[split] = {"n": n, "T": T, "seed": seed, "render_seed": render_seed}
    meta = {
        "generator": {"name": "pgm_wm.datasets.pendulum.simulate_pendulum", "version": VERSION,
                      "params": p, "renderer": "pgm_wm.datasets.pendulum.render_pendulum"},
        "splits": splits_meta,
        "dt": p["dt"],
        "image_shape": [IMAGE_SIZE, IMAGE_SIZE],
        "units": {"obs": "pixel intensity in [0, 1]", "targets": "dimensionless",
                  "angle": "rad", "velocity": "rad/s", "noise_factor": "dimensionless"},
        "obs_names": [f"pixel_{i}_{j}" for i in range(IMAGE_SIZE) for j in range(IMAGE_SIZE)],
        "action_names": [],
        "target_names": ["sin_angle", "cos_angle"],
        "description": "Damped stochastic pendulum rendered as 24x24 images, corrupted by a "
                       "per-sequence random-walk noise factor (first 5 frames clean), ~10% of "
                       "later frames missing. Targets: (sin, cos) of the true angle.",
    }
    return arrays, meta
