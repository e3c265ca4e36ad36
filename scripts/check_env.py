"""Check .venv against requirements.txt for scripts/setup_env.sh (standard library only).

``python scripts/check_env.py``: exit 0 when every ``name==version`` pin of requirements.txt is
installed and pgm_wm is imported from this checkout; 2 when the only difference is that torch is
a CUDA build (the pins want the CPU build); 1 otherwise (one line says what differs,
PGM_WM_SETUP_VERBOSE=1 lists everything).

``python scripts/check_env.py --torch-build``: one line naming the installed torch build.

A local version tag alone does not say "CPU": ``torch 2.13.0`` without a tag from the public
index on Linux is the CUDA build. The CUDA version recorded in ``torch/version.py`` decides.
"""

from __future__ import annotations

import os
import pathlib
import re
import sys
from importlib import metadata

_CUDA = re.compile(r"^cuda(?::[^=]*)?=\s*['\"]([^'\"]+)['\"]", re.M)


def torch_build(version: str, version_py: str) -> tuple[str, bool]:
    """``(description, is_cuda)`` of a torch build from its version string and the text of its
    ``torch/version.py``: ``+cpu`` or no CUDA version -> CPU; ``+cuXXX`` or a CUDA version -> CUDA;
    ``+rocm...`` / others are named by their tag."""
    local = version.partition("+")[2]
    cuda = _CUDA.search(version_py)
    if local.startswith("cu") or cuda:
        return f"CUDA {cuda.group(1) if cuda else local[2:]} build", True
    if local in ("", "cpu"):
        return "CPU build", False
    return f"{local} build", False


def installed_torch_build() -> tuple[str, bool] | None:
    try:
        dist = metadata.distribution("torch")
    except metadata.PackageNotFoundError:
        return None
    files = dist.files or []
    version_py = next((f for f in files if str(f).replace("\\", "/") == "torch/version.py"), None)
    text = version_py.read_text() if version_py is not None else ""
    return torch_build(dist.version, text)


def check(requirements: pathlib.Path, checkout: pathlib.Path) -> tuple[int, str]:
    problems = []
    for raw in requirements.read_text().splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        match = re.fullmatch(r"([A-Za-z0-9_.\-]+)(\[[^\]]*\])?==([^\s;]+)", line)
        if match is None:
            problems.append(f"cannot check requirement line {line!r}")
            continue
        name, wanted = match.group(1), match.group(3)
        try:
            have = metadata.version(name)
        except metadata.PackageNotFoundError:
            problems.append(f"{name} not installed")
            continue
        if have != wanted and have.split("+")[0] != wanted:  # a local tag (+cpu) is judged below
            problems.append(f"{name} {have} installed, {wanted} pinned")
    try:
        import pgm_wm

        here = (checkout / "pgm_wm").resolve()
        if pathlib.Path(pgm_wm.__file__).resolve().parent != here:
            problems.append(f"pgm_wm is imported from {pgm_wm.__file__}, not from {here}")
    except ImportError:
        problems.append("pgm_wm not installed")
    if problems:
        missing = sum(p.endswith("not installed") for p in problems)
        if os.environ.get("PGM_WM_SETUP_VERBOSE") == "1" or len(problems) <= 3:
            detail = "; ".join(problems)
        else:
            detail = f"{missing} not installed, {len(problems) - missing} at another version"
        return 1, f"[setup] .venv needs updating ({detail})"
    build = installed_torch_build()
    if build is not None and build[1]:
        return 2, f"[setup] torch {metadata.version('torch')} is a {build[0]}; the pins want the CPU build"
    return 0, ""


def main(argv: list[str]) -> int:
    if argv[1:] == ["--torch-build"]:
        build = installed_torch_build()
        print("torch not installed" if build is None else f"torch {metadata.version('torch')} ({build[0]})")
        return 0
    root = pathlib.Path.cwd()
    code, message = check(root / "requirements.txt", root)
    if message:
        print(message)
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv))
