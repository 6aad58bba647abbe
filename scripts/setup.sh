#!/usr/bin/env bash
# Set up astrocargo on a fresh machine: system libraries for headless MuJoCo rendering (as root,
# with apt-get), a Python 3.11+ virtual environment in .venv, CPU torch, then the package in
# editable mode with its dev extras. Idempotent; run it from anywhere.
set -euo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."
echo "[setup] repository: $(pwd)"

# Headless rendering: EGL through Mesa (MUJOCO_GL=egl), OSMesa as the software fallback.
APT_PACKAGES=(libegl1 libgl1-mesa-dri libosmesa6)
apt_updated=0
apt_install() {
    if [[ $apt_updated -eq 0 ]]; then
        echo "[setup] apt-get update"
        apt-get update
        apt_updated=1
    fi
    echo "[setup] apt-get install $*"
    DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends "$@"
}

is_root_with_apt() {
    [[ $(id -u) -eq 0 ]] && command -v apt-get >/dev/null 2>&1
}

if is_root_with_apt; then
    missing=()
    for pkg in "${APT_PACKAGES[@]}"; do
        if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
            missing+=("$pkg")
        fi
    done
    if [[ ${#missing[@]} -gt 0 ]]; then
        apt_install "${missing[@]}"
    else
        echo "[setup] system libraries already installed: ${APT_PACKAGES[*]}"
    fi
else
    echo "[setup] not root or no apt-get: skipping system libraries (${APT_PACKAGES[*]})"
fi

# Python 3.11 or newer for the virtual environment.
python_is_311_plus() {
    "$1" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)' >/dev/null 2>&1
}

if [[ -x .venv/bin/python ]] && python_is_311_plus .venv/bin/python; then
    echo "[setup] using existing .venv ($(.venv/bin/python -V))"
else
    PYTHON=""
    for candidate in python3.11 python3; do
        if command -v "$candidate" >/dev/null 2>&1 && python_is_311_plus "$candidate"; then
            PYTHON=$(command -v "$candidate")
            break
        fi
    done
    if [[ -z $PYTHON ]]; then
        echo "[setup] error: need python3.11 (or a python3 that is 3.11+) on PATH" >&2
        exit 1
    fi
    rm -rf .venv
    echo "[setup] creating .venv with $PYTHON ($("$PYTHON" -V))"
    if ! "$PYTHON" -m venv .venv; then
        # Debian's system Python ships venv/ensurepip separately.
        if is_root_with_apt; then
            rm -rf .venv
            ver=$("$PYTHON" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
            apt_install "python${ver}-venv"
            "$PYTHON" -m venv .venv
        else
            echo "[setup] error: '$PYTHON -m venv' failed; install the python3-venv package" >&2
            exit 1
        fi
    fi
fi

PIP=(.venv/bin/python -m pip)
echo "[setup] pip install --upgrade pip"
"${PIP[@]}" install --upgrade pip

# Torch first and pinned: 2.13.0 is a CPU build on this machine's disk; letting pip choose a
# torch for stable-baselines3 would download several GB of CUDA packages.
echo "[setup] pip install torch==2.13.0"
"${PIP[@]}" install torch==2.13.0

echo "[setup] pip install -e .[dev]"
"${PIP[@]}" install -e ".[dev]"

echo "[setup] done: $(.venv/bin/python -V), torch $(.venv/bin/python -c 'import torch; print(torch.__version__)'), mujoco $(.venv/bin/python -c 'import mujoco; print(mujoco.__version__)')"
