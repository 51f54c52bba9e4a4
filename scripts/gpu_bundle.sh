#!/usr/bin/env bash
# Packs what a lent GPU machine lacks of torchir's needs into .gpu/site.tar.xz (git-ignored), to
# carry there with `run(carry=[".gpu"])`: that machine has Python 3.12, torch, lightning, scipy and
# pytest, but no mitsuba, drjit, kornia or jsonargparse, and no network. The cp312 wheels (75 MB)
# are unpacked here and packed as one xz archive (about 43 MB), under the 64 MiB a call carries.
#   bash scripts/gpu_bundle.sh            # then, on the machine: bash scripts/gpu_check.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
PACKAGES=(mitsuba==3.9.1 drjit==1.5.0 kornia==0.9.0 kornia_rs==0.2.0 jsonargparse==4.53.0 docstring_parser==0.18.0
          typeshed_client==2.15.0)
git_exclude() { grep -qx "$1" .git/info/exclude 2>/dev/null || echo "$1" >> .git/info/exclude; }
git_exclude "/.gpu/"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
echo "[gpu_bundle] fetching cp312 wheels: ${PACKAGES[*]}"
$PY -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform any -d "$work/wheels" "${PACKAGES[@]}"
mkdir -p "$work/site"
for w in "$work"/wheels/*.whl; do
    $PY -m zipfile -e "$w" "$work/site"   # a wheel is a zip of its site-packages files
done
mkdir -p .gpu
echo "[gpu_bundle] packing $(du -sh "$work/site" | cut -f1) into .gpu/site.tar.xz"
XZ_OPT=-6T0 tar -cJf .gpu/site.tar.xz -C "$work/site" .
size=$(stat -c %s .gpu/site.tar.xz)
echo "[gpu_bundle] .gpu/site.tar.xz: $((size / 1048576)) MiB"
if [ "$size" -gt $((56 * 1048576)) ]; then
    echo "[gpu_bundle] too large to carry beside the working tree (64 MiB in all)" >&2
    exit 1
fi
