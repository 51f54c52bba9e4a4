#!/usr/bin/env bash
# Installs everything torchir needs on a fresh Debian machine (idempotent):
#   1. LLVM >= 16 for Dr.Jit's CPU backend (Debian's libllvm19) and a C compiler (gcc) for the
#      LOI loss's banded blur kernel, compiled on first use (without one: dense products, slower),
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
apt_updated=""
apt_install() {
    [[ -z "$apt_updated" ]] && $sudo_cmd apt-get update -qq && apt_updated=1
    DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq "$@" >/dev/null
}
if ! has_llvm16plus; then
    echo "[install] LLVM >= 16 not found: installing Debian's libllvm19"
    apt_install libllvm19
fi
if ! command -v "${CC:-cc}" >/dev/null 2>&1; then
    echo "[install] no C compiler found: installing gcc"
    apt_install gcc
fi

PY=${PYTHON:-python3}
if ! $PY -c "import torch" 2>/dev/null; then
    echo "[install] torch (CPU wheel)"
    $PY -m pip install -q torch==2.13.0
fi
echo "[install] torchir${extra}"
$PY -m pip install -q -e ".${extra}"
$PY -c "import torchir; torchir.backend.set_variant('auto'); print('[install] ok:', torchir.backend.describe())"
$PY -c "from torchir.modules._banded import native_available as n; print('[install] LOI banded blur kernel:', 'compiled' if n() else 'unavailable (dense fallback)')"
