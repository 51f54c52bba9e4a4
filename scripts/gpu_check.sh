#!/usr/bin/env bash
# The one prepared command for a lent GPU machine (issue: torchir on CUDA Dr.Jit). From the repo
# root there, with .gpu carried (scripts/gpu_bundle.sh, built here first):
#   run(command="bash scripts/gpu_check.sh", carry=[".gpu"], timeout_s=560)
# Unpacks the carried packages onto PYTHONPATH, prints the versions and whether Dr.Jit's CUDA
# backend and Mitsuba's OptiX render work, runs the test suite on cuda_ad_rgb (TESTS narrows it;
# TEST_SECONDS bounds it), then `torchir bench overhead --quick`, the ReSTIR quick comparison and
# the LOI loss's cost at 512^2, each within its own time limit. Everything lands in $OUT (at most 8 files):
# report.md (the summary), tests.log, bench.log and the benchmarks' results JSON.
# Rehearse it here on the CPU: TORCHIR_VARIANT=llvm_ad_rgb TESTS=tests/functions/test_render.py bash scripts/gpu_check.sh
set -uo pipefail
cd "$(dirname "$0")/.."
OUTDIR=${OUT:-results/gpu_check}
mkdir -p "$OUTDIR"
REPORT=$OUTDIR/report.md
VARIANT=${TORCHIR_VARIANT:-cuda_ad_rgb}
SITE=${TORCHIR_GPU_SITE:-/tmp/torchir_site}
export PYTHONUNBUFFERED=1 TORCHIR_VARIANT=$VARIANT
started=$(date +%s)
elapsed() { echo $(( $(date +%s) - started )); }

extras_used=""
if [ -f .gpu/site.tar.xz ] && [ "$SITE" != none ]; then
    mkdir -p "$SITE" && tar -xJf .gpu/site.tar.xz -C "$SITE" || { echo "unpacking .gpu/site.tar.xz failed" | tee "$REPORT"; exit 1; }
    export PYTHONPATH=$SITE:$PWD${PYTHONPATH:+:$PYTHONPATH}
    # extras: each only where the machine lacks it (a module, then the archive's folders and files)
    if [ -f .gpu/extras.tar.xz ]; then
        for group in "PIL ./PIL ./pillow.libs ./pillow-*" \
                     "matplotlib ./matplotlib ./matplotlib-* ./mpl_toolkits ./contourpy* ./cycler* ./fontTools ./fonttools-* ./kiwisolver* ./pyparsing* ./dateutil ./python_dateutil-* ./six.py ./six-*" \
                     "xdist ./xdist ./pytest_xdist-* ./execnet ./execnet-*"; do
            set -- $group
            module=$1; shift
            if ! python3 -c "import $module" 2>/dev/null; then
                tar -xJf .gpu/extras.tar.xz -C "$SITE" --wildcards "$@" && extras_used="$extras_used $module"
            fi
        done
    fi
else
    export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
fi

{
    echo "# torchir GPU check, $(date -u '+%Y-%m-%d %H:%M UTC'), variant $VARIANT"
    echo
    echo '```'
    nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>&1 | head -2 || true
    EXTRAS_USED="$extras_used" python3 - <<'PY'
import os, platform, time
import numpy, torch
import drjit as dr
import mitsuba as mi
print(f"python {platform.python_version()}, torch {torch.__version__} (cuda {torch.cuda.is_available()}), numpy {numpy.__version__}, "
      f"drjit {dr.__version__}, mitsuba {mi.__version__}")
print("Dr.Jit CUDA backend:", dr.has_backend(dr.JitBackend.CUDA), "| LLVM backend:", dr.has_backend(dr.JitBackend.LLVM))
variant = os.environ["TORCHIR_VARIANT"]
try:
    mi.set_variant(variant)
    scene = mi.load_dict(mi.cornell_box())
    for label in ("first render (kernels compiled)", "second render"):
        start = time.perf_counter()
        image = mi.render(scene, spp=64)
        dr.eval(image); dr.sync_thread()
        print(f"{variant} {label}: {time.perf_counter() - start:.2f} s, mean {float(dr.mean(image.array)[0]):.4f}")
except Exception as error:  # OptiX missing from the driver shows here
    print(f"{variant} render FAILED: {error!r}")
print("extras unpacked (missing here):", os.environ.get("EXTRAS_USED") or "none")
import torchir
print("torchir", torchir.__version__, torchir.backend.describe() if hasattr(torchir.backend, "describe") else "",
      "torch device", torchir.backend.device())
PY
    echo '```'
} 2>&1 | tee "$REPORT"

echo -e "\n## Tests ($VARIANT)\n" >> "$REPORT"
workers=${TEST_WORKERS:-4}
parallel=$(python3 -c "import xdist" 2>/dev/null && echo "-n $workers --dist loadfile" || echo "-p no:xdist")
per_test=$(python3 -c "import pytest_timeout" 2>/dev/null && echo "--timeout 150")
# the files that say most about the GPU first, in case TEST_SECONDS stops the run
export TORCHIR_TESTS_FIRST=${TORCHIR_TESTS_FIRST:-test_device_audit.py,test_render.py,test_render_pixels.py,test_functions_core.py,test_backward_twice.py,test_restir_sampler.py,test_loi.py,test_denoisers.py,test_pixel_sampling.py,test_training_module.py,test_backend.py}
timeout "${TEST_SECONDS:-240}" python3 -m pytest -q -p no:randomly -p no:cacheprovider $parallel \
    $per_test -o addopts="-ra --strict-markers -m 'not slow'" ${TESTS:-tests} > "$OUTDIR/tests.log" 2>&1
rc=$?
{ echo '```'; grep -E "^(FAILED|ERROR)" "$OUTDIR/tests.log" | head -40; tail -3 "$OUTDIR/tests.log"; echo '```'
  echo "pytest exit $rc ($([ $rc -eq 124 ] && echo 'stopped at TEST_SECONDS' || echo done)), $(elapsed) s since start"; } >> "$REPORT"

echo -e "\n## Benchmarks ($VARIANT, quick)\n" >> "$REPORT"
# name:arguments. overhead: a torchir step against plain Mitsuba; restir: its step against B.2's at
# equal samples, and equal-time errors; loi: the loss at 512^2 against a 4-spp render step.
for spec in "overhead:--quick" "restir:--quick" "loi:--quick --only cost --cost-resolution 512"; do
    bench=${spec%%:*}
    timeout "${BENCH_SECONDS:-75}" python3 -m torchir.bench.$bench ${spec#*:} --out "$OUTDIR/bench_$bench" >> "$OUTDIR/bench.log" 2>&1
    rc=$?
    echo "- $bench (${spec#*:}): exit $rc$([ $rc -eq 124 ] && echo ' (stopped at BENCH_SECONDS)'), $(elapsed) s since start" >> "$REPORT"
    [ -f "$OUTDIR/bench_$bench/summary.md" ] && cat "$OUTDIR/bench_$bench/summary.md" >> "$REPORT"
    [ -f "$OUTDIR/bench_$bench/results.json" ] && cp "$OUTDIR/bench_$bench/results.json" "$OUTDIR/${bench}.json"
    rm -rf "$OUTDIR/bench_$bench"   # only 8 files come back
done
echo -e "\ntotal $(elapsed) s" >> "$REPORT"
cat "$REPORT"
