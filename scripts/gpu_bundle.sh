#!/usr/bin/env bash
# Packs what a lent GPU machine lacks of torchir's needs into .gpu/site.tar.xz (git-ignored), to
# carry there with `run(carry=[".gpu"])`: that machine has Python 3.12, torch, lightning, scipy and
# pytest, but no mitsuba, drjit, kornia or jsonargparse, and no network. The cp312 wheels (75 MB)
# are unpacked here and packed as xz archives (site: about 43 MiB; extras: Pillow, matplotlib and
# pytest-xdist, about 9 MiB), under the 64 MiB a call carries with the working tree.
#   bash scripts/gpu_bundle.sh            # then, on the machine: bash scripts/gpu_check.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
PACKAGES=(mitsuba==3.9.1 drjit==1.5.0 kornia==0.9.0 kornia_rs==0.2.0 jsonargparse==4.53.0 docstring_parser==0.18.0
          typeshed_client==2.15.0 cholespy==2.2.0 gpytoolbox==0.3.8)
# Not listed as installed there, needed by the tests and the benchmarks' plots: packed apart
# (.gpu/extras.tar.xz); gpu_check.sh unpacks each only where the machine lacks it.
EXTRAS=(pillow==11.3.0 matplotlib==3.10.3 contourpy==1.3.2 cycler==0.12.1 fonttools==4.58.5 kiwisolver==1.4.8
        pyparsing==3.2.3 python-dateutil==2.9.0.post0 six==1.17.0 pytest-xdist==3.8.0 execnet==2.1.1)
git_exclude() { grep -qx "$1" .git/info/exclude 2>/dev/null || echo "$1" >> .git/info/exclude; }
git_exclude "/.gpu/"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
fetch() {  # fetch DIR PACKAGE...: cp312 wheels, unpacked into DIR
    local dir=$1; shift
    echo "[gpu_bundle] fetching cp312 wheels: $*"
    $PY -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 --platform any -d "$dir.wheels" "$@"
    mkdir -p "$dir"
    for w in "$dir".wheels/*.whl; do
        $PY -m zipfile -e "$w" "$dir"   # a wheel is a zip of its site-packages files
    done
}
fetch "$work/site" "${PACKAGES[@]}"
fetch "$work/extras" "${EXTRAS[@]}"
# matplotlib's PNG path imports five fontTools modules (of 21 MB); no sample data or PDF/PS fonts
find "$work/extras/fontTools" -mindepth 1 -maxdepth 1 ! -name __init__.py ! -name agl.py ! -name misc -exec rm -rf {} +
find "$work/extras/fontTools/misc" -mindepth 1 ! -name __init__.py ! -name loggingTools.py ! -name textTools.py -exec rm -rf {} +
rm -rf "$work/extras/matplotlib/mpl-data/sample_data" \
       "$work/extras/matplotlib/mpl-data/fonts/afm" "$work/extras/matplotlib/mpl-data/fonts/pdfcorefonts"
mkdir -p .gpu
for part in site extras; do
    echo "[gpu_bundle] packing $(du -sh "$work/$part" | cut -f1) into .gpu/$part.tar.xz"
    XZ_OPT=-9T0 tar -cJf ".gpu/$part.tar.xz" -C "$work/$part" .
done
size=$(cat .gpu/*.tar.xz | wc -c)
tree=$(git ls-files -z | xargs -0 cat | wc -c)
echo "[gpu_bundle] .gpu: $((size / 1048576)) MiB, the working tree: $((tree / 1048576)) MiB (a call carries 64 MiB in all)"
if [ $((size + tree)) -gt $((62 * 1048576)) ]; then
    echo "[gpu_bundle] too large to carry beside the working tree" >&2
    exit 1
fi
