# Shared setup for build_book.sh and run_tests.sh (source it, do not run it).
#
# Creates .venv if it is missing, installs the exact pins from requirements.txt and the
# pgm_wm package (editable, from this checkout), then activates the venv. If every pinned
# version is already installed and pgm_wm is importable from this checkout, the install
# step is skipped (a check of well under a second).
#
# torch: on Linux the public package index serves torch==2.13.0 as the CUDA build (about 4 GB
# of nvidia-* packages more). The script first probes the PyTorch CPU wheel index (one HTTPS
# request, at most PGM_WM_PROBE_TIMEOUT seconds; an unresolvable host fails at once) and, when
# it answers, installs torch from there (+cpu). Otherwise torch comes from the configured
# index, and the script says which build it got. Either way it prints the torch build
# (+cpu, +cuXXX, or plain with or without CUDA) and the size of .venv.
#
# Environment variables:
#   PYTHON                 interpreter used to create .venv (default: python3)
#   PGM_WM_REINSTALL       set to 1 to force the pip install step
#   PGM_WM_SETUP_VERBOSE   set to 1 to list every missing or mismatched package
#   PGM_WM_TORCH_INDEX     the CPU wheel index to try (default https://download.pytorch.org/whl/cpu);
#                          "none" skips it (take torch from the configured index, e.g. a CUDA build on purpose)
#   PGM_WM_PROBE_TIMEOUT   seconds to wait for that index (default 5)

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
if (major, minor) < (3, 11):
    print(f"[setup] ERROR: {sys.executable} is Python {major}.{minor}; pgm_wm needs Python 3.11 "
          "or newer. Install Python 3.11 and run again with PYTHON=/path/to/python3.11",
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

TORCH_INDEX="${PGM_WM_TORCH_INDEX:-https://download.pytorch.org/whl/cpu}"
TORCH_PIN=$(grep -E '^torch==' requirements.txt | head -1 | sed -E 's/^torch==([^ ;#]+).*/\1/')

# 0: every pin installed and pgm_wm imported from this checkout; 2: the same, but torch is a
# CUDA build; 1: something to install (scripts/check_env.py says what).
env_is_current() {
    "$VENV/bin/python" scripts/check_env.py
}

# 0 iff the CPU wheel index answers within PGM_WM_PROBE_TIMEOUT seconds (Linux only: elsewhere
# the public index's torch is the CPU build already).
cpu_index_reachable() {
    [ "$TORCH_INDEX" != "none" ] || return 1
    [ "$(uname -s)" = "Linux" ] || return 1
    "$VENV/bin/python" - "$TORCH_INDEX" "${PGM_WM_PROBE_TIMEOUT:-5}" <<'PY'
import sys
import time
import urllib.request

url, timeout = sys.argv[1].rstrip("/") + "/torch/", float(sys.argv[2])
start = time.perf_counter()
try:
    with urllib.request.urlopen(url, timeout=timeout) as reply:
        ok = reply.status == 200
except Exception as err:  # no route, no DNS, a proxy refusing, a timeout
    print(f"[setup] the PyTorch CPU wheel index {url} is not reachable ({type(err).__name__}, "
          f"{time.perf_counter() - start:.1f} s); torch comes from the configured package index")
    sys.exit(1)
sys.exit(0 if ok else 1)
PY
}

# torch==pin from the CPU wheel index (its dependencies come from there or the configured index)
install_cpu_torch() {
    echo "[setup] installing torch==$TORCH_PIN from the CPU wheel index $TORCH_INDEX"
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --index-url "$TORCH_INDEX" \
        --force-reinstall --no-deps "torch==$TORCH_PIN"
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --index-url "$TORCH_INDEX" \
        "torch==$TORCH_PIN"
}

# One line: which torch build is installed and how large .venv is.
report_torch() {
    local size
    size=$(du -sh "$VENV" 2>/dev/null | cut -f1)
    echo "[setup] $("$VENV/bin/python" scripts/check_env.py --torch-build); .venv is ${size:-?}"
}

status=0
if [ "${PGM_WM_REINSTALL:-0}" != "1" ]; then
    env_is_current || status=$?
else
    status=1
fi
if [ "$status" -eq 0 ]; then
    echo "[setup] .venv is up to date"
elif [ "$status" -eq 2 ]; then
    # every pin is there, but torch is a CUDA build: replace it where the CPU build can be had
    if cpu_index_reachable; then
        install_cpu_torch
        echo "[setup] the nvidia-* packages of the CUDA build stay installed; delete .venv for a lean one"
    fi
    report_torch
else
    n_pins=$(grep -cE '^[A-Za-z0-9_.-]+==' requirements.txt)
    echo "[setup] installing $n_pins pinned packages (torch, Jupyter Book, JupyterLab, ...) and pgm_wm into" \
         ".venv: about 2-5 minutes on a first run, seconds when only a pin changed"
    setup_start=$(date +%s)
    have_torch=$("$VENV/bin/python" -c "from importlib.metadata import version; print(version('torch'))" 2>/dev/null || true)
    if [ "${have_torch%%+*}" != "$TORCH_PIN" ] && cpu_index_reachable; then
        install_cpu_torch
    fi
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check -r requirements.txt
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check -e . --no-deps
    "$VENV/bin/python" -m pip check --disable-pip-version-check >/dev/null \
        || { "$VENV/bin/python" -m pip check; exit 1; }
    env_is_current || [ $? -eq 2 ]
    echo "[setup] done in $(( $(date +%s) - setup_start ))s"
    report_torch
fi

# Activate: put the venv's tools (jupyter-book, pytest, the python3 kernel) first on PATH.
export VIRTUAL_ENV="$VENV"
export PATH="$VENV/bin:$PATH"
# Do not set MPLBACKEND here: ipykernel only selects its inline backend when MPLBACKEND
# is unset, and an inherited "Agg" would make every notebook figure disappear.
unset MPLBACKEND
