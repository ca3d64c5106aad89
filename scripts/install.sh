#!/usr/bin/env bash
# Installs everything transtac_sim needs on a fresh Debian machine (idempotent):
#   - system packages: libllvm19 (Mitsuba's CPU variants crash with Debian's default LLVM 15);
#     libsuitesparse-dev (CHOLMOD, built into scikit-sparse: the FEM's sparse Cholesky) and OpenBLAS (CHOLMOD's
#     BLAS; Debian's default reference BLAS makes it ~5x slower)
#   - a virtual environment at .venv with the package (editable) and its test tools, and `trackers` (ByteTrack)
# Usage: bash scripts/install.sh
set -euo pipefail
cd "$(dirname "$0")/.."

need_apt=()
ls /usr/lib/x86_64-linux-gnu/libLLVM.so.19* >/dev/null 2>&1 || ls /usr/lib/*/libLLVM-19.so* >/dev/null 2>&1 || need_apt+=(libllvm19)
[ -f /usr/include/suitesparse/cholmod.h ] || need_apt+=(libsuitesparse-dev)
ls /usr/lib/*/openblas-pthread/libblas.so.3 >/dev/null 2>&1 || need_apt+=(libopenblas0-pthread)
if [ ${#need_apt[@]} -gt 0 ]; then
  echo "[install] system packages: ${need_apt[*]}"
  if [ "$(id -u)" -eq 0 ]; then sudo=""; elif command -v sudo >/dev/null; then sudo="sudo"; else
    echo "[install] error: need root or sudo to apt-get install ${need_apt[*]}" >&2; exit 1; fi
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${need_apt[@]}" >/dev/null
fi

py=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "[install] creating .venv with $($py --version)"
  $py -m venv .venv
fi
stamp=.venv/.transtac_sim_installed
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
  echo "[install] pip install -e .[dev] (first time: a few minutes)"
  .venv/bin/python -m pip install -q -U pip
  .venv/bin/python -m pip install -q -e ".[dev]"
  # ByteTrack: `trackers` declares opencv-python, whose cv2 would overwrite opencv-contrib-python-headless's;
  # its other needs are in pyproject.toml, so it goes in without its declared dependencies.
  .venv/bin/python -m pip install -q --no-deps "trackers==2.6.1"
  touch "$stamp"
fi
echo "[install] ready: .venv/bin/transtac-sim"
