#!/usr/bin/env bash
# Installs everything torchir needs on a fresh Debian machine (idempotent):
#   1. LLVM >= 16 for Dr.Jit's CPU backend (Debian's libllvm19),
#   2. torch's CPU wheel *before* anything that depends on torch, so pip never pulls CUDA packages,
#   3. torchir itself (editable) with its dependencies; pass --dev for the test tools.
set -euo pipefail
cd "$(dirname "$0")/.."

extra=""
[[ "${1:-}" == "--dev" ]] && extra="[dev]"

sudo_cmd=""
[[ $(id -u) -ne 0 ]] && sudo_cmd="sudo"

has_llvm16plus() {
    ldconfig -p 2>/dev/null | grep -Eq 'libLLVM(-|\.so\.)(1[6-9]|[2-9][0-9])'
}
if ! has_llvm16plus; then
    echo "[install] LLVM >= 16 not found: installing Debian's libllvm19"
    $sudo_cmd apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq libllvm19 >/dev/null
fi

PY=${PYTHON:-python3}
if ! $PY -c "import torch" 2>/dev/null; then
    echo "[install] torch (CPU wheel)"
    $PY -m pip install -q torch==2.13.0
fi
echo "[install] torchir${extra}"
$PY -m pip install -q -e ".${extra}"
$PY -c "import torchir; torchir.backend.set_variant('auto'); print('[install] ok:', torchir.backend.describe())"
