"""The package as users install it (issue 24): pyproject's ranges contain the pins, the wheel
carries the datasets and py.typed, and a non-editable install in a fresh virtual environment
loads `pam_arm` and runs the README's Nile script from another folder.

The install test builds the wheel from a copy of the sources and installs it with
``--no-index`` (nothing is downloaded); the fresh environment sees the dependencies of the
running one through a ``.pth`` file. It is skipped where setuptools or venv are missing."""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
import sysconfig
import textwrap
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _pins() -> dict[str, str]:
    pins = {}
    for raw in (ROOT / "requirements.txt").read_text().splitlines():
        line = raw.split("#", 1)[0].strip()
        if "==" in line:
            name, version = line.split("==", 1)
            pins[name.strip().lower()] = version.strip()
    return pins


def test_pyproject_ranges_contain_the_pins():
    from packaging.requirements import Requirement

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    pins = _pins()
    deps = [Requirement(d) for d in project["dependencies"]]
    deps += [Requirement(d) for extra in project.get("optional-dependencies", {}).values() for d in extra]
    assert {d.name for d in deps} >= {"torch", "numpy", "matplotlib", "tqdm", "numba"}
    for dep in deps:
        assert dep.specifier, f"{dep.name}: no version range in pyproject.toml"
        if dep.name.lower() in pins:
            assert dep.specifier.contains(pins[dep.name.lower()]), f"{dep.name}=={pins[dep.name.lower()]} not in {dep}"
    # the classifiers name only Python versions the suite was run on, and the running one is allowed
    versions = [c.rsplit(":: ", 1)[1] for c in project["classifiers"] if c.startswith("Programming Language :: Python :: 3.")]
    assert versions and all(v in ("3.11", "3.12", "3.13") for v in versions)
    from packaging.specifiers import SpecifierSet

    assert SpecifierSet(project["requires-python"]).contains(f"{sys.version_info[0]}.{sys.version_info[1]}")


def _can_build() -> str | None:
    for module in ("setuptools", "wheel", "venv", "pip"):
        if importlib.util.find_spec(module) is None:
            return f"{module} is not installed"
    return None


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    why = _can_build()
    if why:
        pytest.skip(f"cannot build a wheel offline: {why}")
    src = tmp_path_factory.mktemp("src") / "pgm_wm_src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        ".venv", ".git", "_build", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache", ".hypothesis",
        ".jupyter_cache", "_vendor", ".dev", ".ruff_cache", "notebooks", "book", "results", "benchmarks"))
    out = tmp_path_factory.mktemp("wheelhouse")
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                           "-w", str(out), str(src)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (whl,) = out.glob("pgm_wm-*.whl")
    return whl


@pytest.mark.slow
def test_the_wheel_carries_the_data_the_type_marker_and_every_module(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    sums = (ROOT / "data" / "SHA256SUMS").read_text().split()[1::2]
    assert sums and all(f"pgm_wm/data/{f}" in names for f in [*sums, "SHA256SUMS"]), sorted(names)
    assert "pgm_wm/py.typed" in names
    modules = {p.relative_to(ROOT).as_posix() for p in (ROOT / "pgm_wm").rglob("*.py")}
    assert modules <= names, sorted(modules - names)
    with zipfile.ZipFile(wheel) as zf:       # the copies are byte-identical (the digests hold)
        for f in sums:
            assert zf.read(f"pgm_wm/data/{f}") == (ROOT / "data" / f).read_bytes()


@pytest.mark.slow
def test_non_editable_install_loads_pam_arm_and_runs_the_nile_script_elsewhere(wheel, tmp_path):
    env_dir = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env_dir)], check=True, timeout=300)
    py = env_dir / "bin" / "python"
    purelib = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  capture_output=True, text=True, check=True).stdout.strip())
    # the dependencies (torch, numpy, ...) and pip come from the running environment; pgm_wm does not
    (purelib / "zz_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    proc = subprocess.run([str(py), "-m", "pip", "install", "--no-index", "--no-deps", "--ignore-installed",
                           "--disable-pip-version-check", str(wheel)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PGM_WM_DATA", "PYTHONPATH")}
    env["MPLBACKEND"] = "Agg"
    code = textwrap.dedent(f"""
        import pathlib, pgm_wm
        from pgm_wm.datasets import data_dir, load
        from pgm_wm.datasets.loader import restore_command
        here = pathlib.Path(pgm_wm.__file__).resolve().parent
        assert here.is_relative_to(pathlib.Path({str(purelib)!r}).resolve()), here   # the installed copy
        assert data_dir() == here / "data", data_dir()
        d = load("pam_arm", "test")
        assert d.obs.shape[0] == 92
        assert "git" not in restore_command("pam_arm"), restore_command("pam_arm")
        import importlib, pkgutil
        for m in pkgutil.walk_packages(pgm_wm.__path__, "pgm_wm."):
            if not m.name.endswith("__main__"):
                importlib.import_module(m.name)
        print("ok", d.obs.shape)
    """)
    proc = subprocess.run([str(py), "-c", code], cwd=elsewhere, capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.startswith("ok")
    # PGM_WM_DATA still overrides the packaged copy
    mine = tmp_path / "mine"
    mine.mkdir()
    shutil.copy(ROOT / "data" / "nile.csv", mine)
    lines = (ROOT / "data" / "SHA256SUMS").read_text().splitlines()
    (mine / "SHA256SUMS").write_text("".join(line + "\n" for line in lines if line.endswith("nile.csv")))
    proc = subprocess.run([str(py), "-c", "from pgm_wm.datasets import data_dir, load; load('nile'); print(data_dir())"],
                          cwd=elsewhere, capture_output=True, text=True, env={**env, "PGM_WM_DATA": str(mine)}, timeout=300)
    assert proc.returncode == 0 and proc.stdout.strip() == str(mine), proc.stdout + proc.stderr
    # the README's Nile script, verbatim
    from test_lgssm import _readme_block

    (elsewhere / "nile.py").write_text(_readme_block("<!-- nile-script -->"))
    proc = subprocess.run([str(py), "-W", "error::UserWarning", "nile.py"], cwd=elsewhere, capture_output=True,
                          text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (elsewhere / "nile.png").exists()


def test_check_env_does_not_take_a_cuda_torch_for_the_cpu_pin():
    """scripts/check_env.py (used by setup_env.sh): a version tag alone does not mean CPU."""
    spec = importlib.util.spec_from_file_location("check_env", ROOT / "scripts" / "check_env.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    none = "cuda: Optional[str] = None\n"
    assert mod.torch_build("2.13.0+cpu", none) == ("CPU build", False)
    assert mod.torch_build("2.13.0", none) == ("CPU build", False)                  # macOS / Windows wheels
    assert mod.torch_build("2.13.0+cu130", "cuda: Optional[str] = '13.0'\n") == ("CUDA 13.0 build", True)
    assert mod.torch_build("2.13.0", "cuda: Optional[str] = '12.8'\n") == ("CUDA 12.8 build", True)   # PyPI, Linux
    assert mod.torch_build("2.13.0+cu126", "") == ("CUDA 126 build", True)
    assert mod.torch_build("2.13.0+rocm6.4", none) == ("rocm6.4 build", False)
