# Shared setup for build_book.sh and run_tests.sh (source it, do not run it).
#
# Creates .venv if it is missing, installs the exact pins from requirements.txt and the
# pgm_wm package (editable, from this checkout), then activates the venv. If every pinned
# version is already installed and pgm_wm is importable from this checkout, the install
# step is skipped (a check of well under a second).
#
# Environment variables:
#   PYTHON            interpreter used to create .venv (default: python3)
#   PGM_WM_REINSTALL  set to 1 to force the pip install step

set -euo pipefail

REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO_ROOT"
VENV="$REPO_ROOT/.venv"

if [ ! -x "$VENV/bin/python" ]; then
    echo "[setup] creating virtual environment in .venv with ${PYTHON:-python3}"
    "${PYTHON:-python3}" -m venv "$VENV"
fi

# Exit status 0 iff every 'name==version' pin in requirements.txt is installed and
# pgm_wm is imported from this checkout's pgm_wm/ folder.
env_is_current() {
    "$VENV/bin/python" - <<'PY'
import pathlib
import re
import sys
from importlib import metadata

problems = []
for raw in pathlib.Path("requirements.txt").read_text().splitlines():
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
    if have != wanted and have.split("+")[0] != wanted:  # accept local tags, e.g. 2.13.0+cpu
        problems.append(f"{name} {have} installed, {wanted} pinned")
try:
    import pgm_wm

    here = (pathlib.Path.cwd() / "pgm_wm").resolve()
    if pathlib.Path(pgm_wm.__file__).resolve().parent != here:
        problems.append(f"pgm_wm is imported from {pgm_wm.__file__}, not from {here}")
except ImportError:
    problems.append("pgm_wm not installed")
for problem in problems:
    print(f"[setup] {problem}")
sys.exit(1 if problems else 0)
PY
}

if [ "${PGM_WM_REINSTALL:-0}" != "1" ] && env_is_current; then
    echo "[setup] .venv is up to date"
else
    echo "[setup] installing requirements.txt and pgm_wm (editable) into .venv"
    "$VENV/bin/python" -m pip install --quiet -r requirements.txt
    "$VENV/bin/python" -m pip install --quiet -e . --no-deps
    "$VENV/bin/python" -m pip check
    env_is_current
fi

# Activate: put the venv's tools (jupyter-book, pytest, the python3 kernel) first on PATH.
export VIRTUAL_ENV="$VENV"
export PATH="$VENV/bin:$PATH"
# Do not set MPLBACKEND here: ipykernel only selects its inline backend when MPLBACKEND
# is unset, and an inherited "Agg" would make every notebook figure disappear.
unset MPLBACKEND
