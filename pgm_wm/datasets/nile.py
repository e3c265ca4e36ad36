"""The Nile series: annual flow volume of the Nile at Aswan, 1871-1970 (real data).

Source: G. W. Cobb (1978), "The problem of the Nile: conditional solution to a
changepoint problem", Biometrika 65(2), 243-251; the same 100 numbers are the
running example of Durbin & Koopman, *Time Series Analysis by State Space
Methods*, and ship as ``Nile`` in R's ``datasets`` package and as
``statsmodels.datasets.nile``. Public domain. Units: 10^8 m^3 per year.

Summary statistics (checked in the tests): sum 91935, mean 919.35, sample
standard deviation 169.23, median 893.5, minimum 456 (1913), maximum 1370 (1879).
The drop in level around 1899 coincides with the first Aswan dam.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["NILE_FIRST_YEAR", "NILE_FLOW", "write_nile_csv", "read_nile_csv"]

NILE_FIRST_YEAR = 1871

# 100 annual volumes, 1871..1970, ten per line (one decade per line).
NILE_FLOW: tuple[int, ...] = (
    1120, 1160, 963, 1210, 1160, 1160, 813, 1230, 1370, 1140,   # 1871-1880
    995, 935, 1110, 994, 1020, 960, 1180, 799, 958, 1140,       # 1881-1890
    1100, 1210, 1150, 1250, 1260, 1220, 1030, 1100, 774, 840,   # 1891-1900
    874, 694, 940, 833, 701, 916, 692, 1020, 1050, 969,         # 1901-1910
    831, 726, 456, 824, 702, 1120, 1100, 832, 764, 821,         # 1911-1920
    768, 845, 864, 862, 698, 845, 744, 796, 1040, 759,          # 1921-1930
    781, 865, 845, 944, 984, 897, 822, 1010, 771, 676,          # 1931-1940
    649, 846, 812, 742, 801, 1040, 860, 874, 848, 890,          # 1941-1950
    744, 749, 838, 1050, 918, 986, 797, 923, 975, 815,          # 1951-1960
    1020, 906, 901, 1170, 912, 746, 919, 718, 714, 740,         # 1961-1970
)

_HEADER = "year,volume"


def write_nile_csv(path: str | os.PathLike) -> Path:
    """Write the series as a two-column CSV (``year,volume``), one row per year."""
    path = Path(path)
    rows = [_HEADER] + [f"{NILE_FIRST_YEAR + i},{v}" for i, v in enumerate(NILE_FLOW)]
    path.write_text("\n".join(rows) + "\n")
    return path


def read_nile_csv(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read the CSV written by :func:`write_nile_csv`; returns ``(years, volume)``, each ``(100,)``."""
    lines = Path(path).read_text().strip().splitlines()
    if lines[0].strip() != _HEADER:
        raise ValueError(f"path: {path} does not look like the Nile CSV (header {lines[0]!r})")
    years, volume = zip(*(line.split(",") for line in lines[1:]))
    return np.asarray(years, dtype=np.int64), np.asarray(volume, dtype=np.float64)
