#!/usr/bin/env bash
# Set up lfsim on a fresh Debian/Ubuntu machine: a recent libLLVM for Dr.Jit's
# CPU back end (the distribution's LLVM 15 aborts on Dr.Jit kernels), then a
# virtual environment in .venv with lfsim and its test extras.
set -euo pipefail
cd "$(dirname "$0")/.."

have_llvm() {
  ldconfig -p 2>/dev/null | grep -Eq 'libLLVM(-|\.so\.)(1[6-9]|[2-9][0-9])' \
    || [ -n "${DRJIT_LIBLLVM_PATH:-}" ]
}
if ! have_llvm; then
  SUDO=""
  [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  echo "lfsim setup: installing libllvm19 (needed by Dr.Jit's LLVM back end)"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19 >/dev/null
fi

PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[test,peers]'
# rayoptics reads CODE V and Zemax files: the peer of lfsim's lens-file import in the
# tests. Its wheel (and opticalglass's) asks for Qt and Jupyter, which the file readers do
# not use: they are installed without their declared dependencies (the `peers` extra above
# has what the readers import).
.venv/bin/python -m pip install -q --no-deps rayoptics==0.9.8 opticalglass==1.1.1
echo "lfsim setup: done ($(.venv/bin/lfsim --version))"
