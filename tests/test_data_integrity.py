"""load() trusts no file it has not checked against data/SHA256SUMS (issue 13, finding 1).

Every corruption below is made on a temporary copy of the data folder; the
committed files are never touched.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pgm_wm.datasets import DataFileError, data_dir, load
from pgm_wm.datasets import _io
from pgm_wm.datasets._io import read_npz, write_npz, write_sha256sums

SMALL_FILES = ("nile.csv", "tracking.npz")


@pytest.fixture
def folder(tmp_path, monkeypatch):
    """A copy of nile.csv, tracking.npz and their SHA256SUMS lines, used by load()."""
    out = tmp_path / "data"
    out.mkdir()
    for name in SMALL_FILES:
        shutil.copy2(data_dir() / name, out / name)
    lines = [line for line in (data_dir() / "SHA256SUMS").read_text().splitlines()
             if line.split()[-1] in SMALL_FILES]
    (out / "SHA256SUMS").write_text("\n".join(lines) + "\n")
    monkeypatch.setenv("PGM_WM_DATA", str(out))
    _io.clear_verified_cache()
    return out


def _touch_later(path: Path) -> None:
    """Move the modification time forward, as any real edit would."""
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 2_000_000_000))


def _expect_named_error(name: str, filename: str, **kw) -> DataFileError:
    with pytest.raises(DataFileError) as err:
        load(name, **kw)
    msg = str(err.value)
    assert filename in msg and f"python -m pgm_wm.datasets build --only {name}" in msg, msg
    assert isinstance(err.value, ValueError)
    return err.value


def test_the_copy_loads_like_the_original(folder):
    assert float(load("nile").obs[0, 0, 0]) == 1120.0
    np.testing.assert_array_equal(load("tracking", "test").obs.numpy(), load_original("tracking", "test"))


def load_original(name: str, split: str) -> np.ndarray:
    arrays, _ = read_npz(data_dir() / f"{name}.npz")
    return arrays[f"{split}__obs"]


def test_one_changed_digit_in_nile_csv_is_refused(folder):
    path = folder / "nile.csv"
    text = path.read_text()
    assert "1871,1120\n" in text
    path.write_text(text.replace("1871,1120\n", "1871,1920\n"))
    _expect_named_error("nile", "nile.csv")


def test_nile_csv_cut_to_half_its_rows_is_refused(folder):
    path = folder / "nile.csv"
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines[:51]) + "\n")
    _expect_named_error("nile", "nile.csv")


def test_rewritten_npz_with_one_value_changed_is_refused(folder):
    path = folder / "tracking.npz"
    arrays, meta = read_npz(path)
    arrays["train__obs"] = arrays["train__obs"].copy()
    arrays["train__obs"][3, 7, 0] += 100.0
    write_npz(path, arrays, meta)  # a perfectly valid npz, only the digest tells
    _expect_named_error("tracking", "tracking.npz")


def test_flipped_byte_inside_a_zip_member_is_refused_for_every_split(folder):
    path = folder / "tracking.npz"
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    path.write_bytes(bytes(raw))
    for split in ("train", "test"):  # not only the split whose member was hit
        _expect_named_error("tracking", "tracking.npz", split=split)


@pytest.mark.parametrize("keep", [0.5, 0.02])
def test_truncated_npz_is_refused(folder, keep):
    path = folder / "tracking.npz"
    raw = path.read_bytes()
    path.write_bytes(raw[: int(len(raw) * keep)])
    _expect_named_error("tracking", "tracking.npz")


def test_damaged_file_with_matching_digest_still_gives_one_named_error(folder):
    """Someone re-ran sha256sum over a damaged file: the read error is still named."""
    path = folder / "tracking.npz"
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) // 2])
    write_sha256sums(folder, list(SMALL_FILES))
    err = _expect_named_error("tracking", "tracking.npz")
    assert "cannot be read" in str(err)


def test_unlisted_file_and_missing_sums_are_refused(folder):
    lines = (folder / "SHA256SUMS").read_text().splitlines()
    (folder / "SHA256SUMS").write_text("\n".join(line for line in lines if "nile" not in line) + "\n")
    err = _expect_named_error("nile", "nile.csv")
    assert "not listed" in str(err)
    (folder / "SHA256SUMS").unlink()
    _expect_named_error("tracking", "SHA256SUMS")


def test_missing_file_names_the_restore_command(folder):
    (folder / "tracking.npz").unlink()
    with pytest.raises(FileNotFoundError, match="build --only tracking"):
        load("tracking")


def test_verdict_is_cached_by_size_and_mtime(folder, monkeypatch):
    calls = []
    real = _io.sha256_file
    monkeypatch.setattr(_io, "sha256_file", lambda p: calls.append(p) or real(p))
    load("tracking", "train")
    load("tracking", "test")
    load("tracking", "train")
    assert len(calls) == 1  # hashed once for three loads
    # an edit of the same size is noticed because the modification time moves
    path = folder / "tracking.npz"
    raw = bytearray(path.read_bytes())
    raw[len(raw) // 3] ^= 0x01
    path.write_bytes(bytes(raw))
    _touch_later(path)
    _expect_named_error("tracking", "tracking.npz")
    assert len(calls) == 2


def test_repeated_loads_of_committed_files_hash_once(monkeypatch):
    """On the committed files: the first load of a file hashes it, repeated loads do not."""
    _io.clear_verified_cache()
    calls = []
    real = _io.sha256_file
    monkeypatch.setattr(_io, "sha256_file", lambda p: calls.append(Path(p).name) or real(p))
    for _ in range(3):
        load("payload_arm", "valid")
        load("hysteresis_arm", "test")
    assert sorted(calls) == ["hysteresis_arm.npz", "payload_arm.npz"]


def test_cli_check_with_a_deleted_file_exits_nonzero_without_traceback(folder):
    (folder / "nile.csv").unlink()
    proc = subprocess.run([sys.executable, "-m", "pgm_wm.datasets", "check", "--dir", str(folder)],
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    assert proc.returncode == 1
    assert "Traceback" not in proc.stderr + proc.stdout
    assert "nile.csv: MISSING" in proc.stdout
    assert "build --only nile" in proc.stdout
    assert "tracking.npz: OK" in proc.stdout


# ----------------------------------------------------------------------------- issue 24


def test_same_size_edit_with_the_modification_time_put_back_is_noticed(folder):
    """The verdict cache must not trust size + mtime alone: an edit of the same size whose mtime
    is restored with os.utime (what `cp -p`, `rsync -t` or `touch -r` do) is hashed again."""
    assert float(load("nile").obs[0, 0, 0]) == 1120.0       # verified and cached
    path = folder / "nile.csv"
    st = path.stat()
    text = path.read_text()
    time.sleep(0.02)                                         # past the file system's clock tick
    path.write_text(text.replace(",1120", ",1121", 1))       # one digit: same size, readable, wrong
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert path.stat().st_size == st.st_size and path.stat().st_mtime_ns == st.st_mtime_ns
    err = _expect_named_error("nile", "nile.csv")
    assert "does not match" in str(err)


def test_unreadable_file_gives_the_promised_data_file_error(folder):
    """A file that exists but cannot be read is a DataFileError naming it, not a raw OSError."""
    path = folder / "tracking.npz"
    path.unlink()
    path.mkdir()                                   # a folder where the file should be: unreadable as a file
    err = _expect_named_error("tracking", "tracking.npz")
    assert "cannot be read" in str(err)


def test_permission_denied_gives_the_promised_data_file_error(folder, monkeypatch):
    """No read permission (as any non-root user gets from `chmod 000`). Root may read anything, so
    the denial is made by the file system call itself."""
    real_open = open

    def deny(file, *args, **kwargs):
        if str(file).endswith("tracking.npz"):
            raise PermissionError(13, "Permission denied", str(file))
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr("builtins.open", deny)
    err = _expect_named_error("tracking", "tracking.npz")
    assert "PermissionError" in str(err)


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads files whatever their permission bits")
def test_chmod_000_gives_the_promised_data_file_error(folder):
    path = folder / "tracking.npz"
    path.chmod(0)
    try:
        _expect_named_error("tracking", "tracking.npz")
    finally:
        path.chmod(0o644)


def test_restore_hints_make_sense_outside_a_clone(monkeypatch, tmp_path):
    """In a clone: git / the build command. From an installed wheel (data inside the package) and
    with PGM_WM_DATA: no `git checkout`, which means nothing outside a clone."""
    from pgm_wm.datasets import loader

    monkeypatch.delenv("PGM_WM_DATA", raising=False)
    monkeypatch.setattr(loader, "_package_data_dir", lambda: None)
    assert loader.restore_command("pam_arm") == "git checkout -- data/pam_arm.npz"
    assert loader.restore_command("tracking") == "python -m pgm_wm.datasets build --only tracking"
    monkeypatch.setattr(loader, "_package_data_dir", lambda: tmp_path)          # an installed wheel
    assert loader.data_dir() == tmp_path
    assert "git" not in loader.restore_command("pam_arm")
    assert "pip install --force-reinstall --no-deps pgm_wm" in loader.restore_command("pam_arm")
    assert loader.restore_command("nile") == "python -m pgm_wm.datasets build --only nile"
    monkeypatch.setenv("PGM_WM_DATA", str(tmp_path / "mine"))                    # the override wins
    assert loader.data_dir() == tmp_path / "mine"
    assert "git" not in loader.restore_command("pam_arm") and "PGM_WM_DATA" in loader.restore_command("pam_arm")
    assert loader.restore_command("tracking") == (f"PGM_WM_DATA={tmp_path / 'mine'} "
                                                  "python -m pgm_wm.datasets build --only tracking")
