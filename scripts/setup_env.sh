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
#   PGM_WM_SETUP_VERBOSE  set to 1 to list every missing or mismatched package

set -euo pipefail

REPO_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO_ROOT"
VENV="$REPO_ROOT/.venv"

# The pins in requirements.txt are verified on Python 3.11 (README). Check the interpreter
# before creating anything, with a message that says what to do.
check_python() {
    "$1" - <<'PY'
import sys
major, minor = sys.version_info[:2]
if (major, minor) < (3, 10):
    print(f"[setup] ERROR: {sys.executable} is Python {major}.{minor}; pgm_wm needs Python 3.11 "
          "(3.10 or newer). Install Python 3.11 and run again with PYTHON=/path/to/python3.11",
          file=sys.stderr)
    sys.exit(1)
if (major, minor) != (3, 11):
    print(f"[setup] note: Python {major}.{minor}; the pinned versions are tested on 3.11 "
          "(set PYTHON=/path/to/python3.11 to use it)", file=sys.stderr)
PY
}

if [ ! -x "$VENV/bin/python" ]; then
    py="${PYTHON:-python3}"
    if ! command -v "$py" >/dev/null 2>&1; then
        echo "[setup] ERROR: '$py' not found; install Python 3.11 or set PYTHON=/path/to/python3.11" >&2
        exit 1
    fi
    check_python "$py"
    echo "[setup] creating virtual environment in .venv with $("$py" --version 2>&1)"
    "$py" -m venv "$VENV"
else
    check_python "$VENV/bin/python"
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
# One line instead of one per package (PGM_WM_SETUP_VERBOSE=1 lists them all).
if problems:
    import os

    missing = sum(p.endswith("not installed") for p in problems)
    if os.environ.get("PGM_WM_SETUP_VERBOSE") == "1" or len(problems) <= 3:
        detail = "; ".join(problems)
    else:
        detail = f"{missing} not installed, {len(problems) - missing} at another version"
    print(f"[setup] .venv needs updating ({detail})")
sys.exit(1 if problems else 0)
PY
}

if [ "${PGM_WM_REINSTALL:-0}" != "1" ] && env_is_current; then
    echo "[setup] .venv is up to date"
else
    n_pins=$(grep -cE '^[A-Za-z0-9_.-]+==' requirements.txt)
    echo "[setup] installing $n_pins pinned packages (torch CPU, Jupyter Book, JupyterLab, ...;" \
         "a few hundred MB) and pgm_wm into .venv: about 2-5 minutes on a first run, seconds" \
         "when only a pin changed"
    setup_start=$(date +%s)
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check -r requirements.txt
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check -e . --no-deps
    "$VENV/bin/python" -m pip check --disable-pip-version-check >/dev/null \
        || { "$VENV/bin/python" -m pip check; exit 1; }
    env_is_current
    echo "[setup] done in $(( $(date +%s) - setup_start ))s"
fi

# Activate: put the venv's tools (jupyter-book, pytest, the python3 kernel) first on PATH.
export VIRTUAL_ENV="$VENV"
export PATH="$VENV/bin:$PATH"
# Do not set MPLBACKEND here: ipykernel only selects its inline backend when MPLBACKEND
# is unset, and an inherited "Agg" would make every notebook figure disappear.
unset MPLBACKEND
