#!/usr/bin/env bash
# Set up astrocargo on a fresh machine: system libraries for headless MuJoCo rendering (as root,
# with apt-get), a Python 3.11+ virtual environment in .venv, CPU torch, then the package in
# editable mode. Idempotent; run it from anywhere.
#
#   bash scripts/setup.sh         what the demo, benchmarks and SB3 training need (core + torch)
#   bash scripts/setup.sh --dev   also the test and lint tools and the Ray extra (CI, the test suite)
set -euo pipefail

usage() {
    echo "usage: bash scripts/setup.sh [--dev]" >&2
    echo "  --dev  also install the dev extra (pytest, hypothesis, ruff) and the ray extra" >&2
}

EXTRAS=""
for arg in "$@"; do
    case "$arg" in
        --dev) EXTRAS="[dev]" ;;
        -h | --help)
            usage
            exit 0
            ;;
        *)
            echo "[setup] error: unknown argument '$arg'" >&2
            usage
            exit 2
            ;;
    esac
done

cd "$(dirname "${BASH_SOURCE[0]}")/.."
echo "[setup] repository: $(pwd)"

# Headless rendering: EGL through Mesa (MUJOCO_GL=egl), OSMesa as the software fallback.
APT_PACKAGES=(libegl1 libgl1-mesa-dri libosmesa6)
# Another apt-get (an unattended upgrade, a second set-up) may hold apt's locks: wait for them,
# bounded. DPkg::Lock::Timeout makes apt-get wait for dpkg's lock; apt-get update also takes the
# lists lock (/var/lib/apt/lists/lock), which older apt versions do not wait for, so update is
# retried for up to APT_LOCK_TIMEOUT_S as well.
APT_LOCK_TIMEOUT_S=120
APT_OPTS=(-o "DPkg::Lock::Timeout=$APT_LOCK_TIMEOUT_S")
apt_updated=0
apt_update() {
    local waited=0
    echo "[setup] apt-get update"
    until apt-get "${APT_OPTS[@]}" update; do
        if [[ $waited -ge $APT_LOCK_TIMEOUT_S ]]; then
            echo "[setup] error: apt-get update failed for ${APT_LOCK_TIMEOUT_S} s" >&2
            return 1
        fi
        echo "[setup] apt-get update failed (another apt-get holding the lock?); retrying in 10 s"
        sleep 10
        waited=$((waited + 10))
    done
}
apt_install() {
    if [[ $apt_updated -eq 0 ]]; then
        apt_update
        apt_updated=1
    fi
    echo "[setup] apt-get install $*"
    DEBIAN_FRONTEND=noninteractive apt-get "${APT_OPTS[@]}" install -y --no-install-recommends "$@"
}

is_root_with_apt() {
    [[ $(id -u) -eq 0 ]] && command -v apt-get >/dev/null 2>&1
}

missing=()
if command -v dpkg-query >/dev/null 2>&1; then
    for pkg in "${APT_PACKAGES[@]}"; do
        if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
            missing+=("$pkg")
        fi
    done
    if [[ ${#missing[@]} -eq 0 ]]; then
        # Nothing to install: apt-get (update included) is not run at all.
        echo "[setup] system libraries already installed: ${APT_PACKAGES[*]}"
    elif is_root_with_apt; then
        apt_install "${missing[@]}"
    else
        echo "[setup] warning: missing ${missing[*]} (rendering needs them); as root:" \
            "apt-get install ${missing[*]}" >&2
    fi
else
    echo "[setup] no dpkg: skipping system libraries (${APT_PACKAGES[*]} or their equivalents)"
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

echo "[setup] pip install -e .${EXTRAS}"
"${PIP[@]}" install -e ".${EXTRAS}"

echo "[setup] done: $(.venv/bin/python -V), torch $(.venv/bin/python -c 'import torch; print(torch.__version__)'), mujoco $(.venv/bin/python -c 'import mujoco; print(mujoco.__version__)')"
