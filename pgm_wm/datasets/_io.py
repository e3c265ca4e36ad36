"""File input/output for the bundled datasets: deterministic ``.npz`` and checksums.

``numpy.savez_compressed`` stamps every member of the zip archive with the
current time, so two builds of the same arrays give different bytes. The
writer below fixes the timestamp (and every other zip header field), so a
rebuild on the same machine reproduces the file byte for byte and
``data/SHA256SUMS`` stays stable. The result is an ordinary ``.npz`` file:
``numpy.load(path, allow_pickle=False)`` reads it.

Layout of one dataset file ``data/<name>.npz``:

- ``"<split>__<array>"``: float32 / bool arrays, e.g. ``"train__obs"``;
- ``"meta_json"``: a 0-d unicode array holding a JSON document with the
  generator name, version, seed, parameters and per-split information.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from pathlib import Path
from typing import Mapping

import numpy as np

__all__ = [
    "SEP",
    "META_KEY",
    "write_npz",
    "read_npz",
    "sha256_file",
    "write_sha256sums",
    "read_sha256sums",
    "DataFileError",
    "verify_file",
    "clear_verified_cache",
]

SEP = "__"
META_KEY = "meta_json"
# The earliest date a zip header can hold; any fixed value makes the bytes reproducible.
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


def write_npz(path: str | os.PathLike, arrays: Mapping[str, np.ndarray], meta: Mapping) -> None:
    """Write ``arrays`` plus ``meta`` (JSON) to a compressed, byte-reproducible ``.npz``.

    Members are written in sorted key order with a fixed timestamp and
    permission bits; ``meta`` is stored as the 0-d unicode array ``"meta_json"``
    (``json.dumps`` with sorted keys), so no pickling is ever needed.
    """
    if META_KEY in arrays:
        raise ValueError(f"arrays: the key {META_KEY!r} is reserved for the metadata")
    members = {key: np.asarray(arrays[key]) for key in sorted(arrays)}
    for key, val in members.items():
        if val.dtype == object:
            raise ValueError(f"arrays: {key!r} has dtype object, which would need pickle")
    members[META_KEY] = np.asarray(json.dumps(meta, sort_keys=True, indent=1))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with zipfile.ZipFile(tmp, mode="w", compression=zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for key, val in members.items():
            info = zipfile.ZipInfo(key + ".npy", date_time=_ZIP_EPOCH)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asarray(val, order="C"), allow_pickle=False)
            zf.writestr(info, buf.getvalue(), compress_type=zipfile.ZIP_DEFLATED, compresslevel=9)
    os.replace(tmp, path)


def read_npz(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict]:
    """Read a file written by :func:`write_npz`; returns ``(arrays, meta)`` without pickle."""
    with np.load(path, allow_pickle=False) as data:
        arrays = {key: data[key] for key in data.files if key != META_KEY}
        meta = json.loads(str(data[META_KEY][()]))
    return arrays, meta


def sha256_file(path: str | os.PathLike) -> str:
    """Hex SHA-256 digest of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_sha256sums(data_dir: str | os.PathLike, filenames: list[str]) -> Path:
    """Write ``SHA256SUMS`` (``sha256sum`` format: ``<hex>  <name>``) for ``filenames``."""
    data_dir = Path(data_dir)
    lines = [f"{sha256_file(data_dir / name)}  {name}\n" for name in sorted(filenames)]
    out = data_dir / "SHA256SUMS"
    out.write_text("".join(lines))
    return out


def read_sha256sums(data_dir: str | os.PathLike) -> dict[str, str]:
    """Parse ``data_dir/SHA256SUMS`` into ``{filename: hex digest}``."""
    sums = {}
    path = Path(data_dir) / "SHA256SUMS"
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if line.strip():
            parts = line.split(maxsplit=1)
            if len(parts) != 2 or len(parts[0]) != 64:
                raise ValueError(f"{path}: line {number} is not '<sha256 hex>  <name>': {line!r}")
            sums[parts[1].strip().lstrip("*")] = parts[0].lower()
    return sums


class DataFileError(ValueError):
    """A bundled data file is missing from ``SHA256SUMS``, does not match its digest, or cannot be read.

    The message names the file and the command that restores it.
    """


# (resolved path, device, inode, size, mtime_ns, ctime_ns, expected digest) of files whose digest
# matched. The change time (ctime) moves on every write and on every os.utime call and cannot be
# set back by a user, so an edit of the same size whose modification time was restored is noticed.
_VERIFIED: set[tuple[str, int, int, int, int, int, str]] = set()


def _stat_key(path: Path, expected: str) -> tuple[str, int, int, int, int, int, str]:
    st = path.stat()
    return (str(path.resolve()), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns, expected)


def verify_file(path: str | os.PathLike, restore: str) -> Path:
    """Check ``path`` against the ``SHA256SUMS`` of its folder; return the path.

    The verdict is cached by the file's identity and status (inode, size, modification and
    change times), so a file is hashed once per process unless it changes; any write, even one
    that keeps the size and puts the modification time back, changes the change time.
    ``restore`` is the command quoted in the error.

    Raises:
        FileNotFoundError: the file does not exist (the message quotes ``restore``).
        DataFileError: ``SHA256SUMS`` is missing or does not list the file, the file's SHA-256
            differs from the listed one, or the file cannot be read (no permission, a folder, ...).
    """
    path = Path(path)
    try:
        exists = path.exists()
    except OSError as err:  # e.g. a folder on the way without search permission
        raise DataFileError(f"{path}: cannot be read ({type(err).__name__}: {err}); "
                            f"restore it with `{restore}`") from err
    if not exists:
        raise FileNotFoundError(f"{path} not found; restore it with `{restore}`")
    try:
        sums = read_sha256sums(path.parent)
    except (OSError, ValueError) as err:
        raise DataFileError(f"{path.parent / 'SHA256SUMS'}: cannot be read ({err}); "
                            f"restore it with `{restore}`") from err
    expected = sums.get(path.name)
    if expected is None:
        raise DataFileError(f"{path}: not listed in {path.parent / 'SHA256SUMS'}; restore it with `{restore}`")
    try:
        key = _stat_key(path, expected)
        if key in _VERIFIED:
            return path
        actual = sha256_file(path)
    except OSError as err:  # PermissionError, IsADirectoryError, an I/O error
        raise DataFileError(f"{path}: cannot be read ({type(err).__name__}: {err}); "
                            f"restore it with `{restore}`") from err
    if actual != expected:
        raise DataFileError(
            f"{path}: SHA-256 {actual[:16]}... does not match {expected[:16]}... in SHA256SUMS "
            f"(the file is corrupt, truncated or was edited); restore it with `{restore}`")
    _VERIFIED.add(key)
    return path


def clear_verified_cache() -> None:
    """Forget every cached checksum verdict (the next load hashes its file again)."""
    _VERIFIED.clear()
