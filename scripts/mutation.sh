#!/usr/bin/env bash
# Mutation testing of torchir's numerical cores with mutmut (pip install -e '.[mutation]').
# Not run in CI: it is slow. Usage:
#
#   scripts/mutation.sh [--budget MINUTES] [--workdir DIR] [FILE ...]
#
# FILE: modules under torchir/ to mutate (default: every file of the map below). Each file is
# mutated in its own copy of the tree, DIR/<name>/ (default /tmp/torchir-mutation), against
# only the test files that cover it, under `nice -n 15`, one child process. Re-running the
# same command resumes: mutmut keeps each mutant's result in DIR/<name>/mutants/ and skips
# the ones already tested (delete DIR/<name> after changing the code or its tests). The
# budget (default 30 min) is per file; what it leaves unchecked shows as "not checked".
# The report, DIR/report.md, gives per file: killed, timeout, survived, no tests, not checked
# and the score killed+timeout / (killed+timeout+survived); then each survivor's diff, to be
# annotated (caught now / equivalent mutant / accepted, why).
set -euo pipefail

budget=30
workdir=/tmp/torchir-mutation
files=()
while [[ $# -gt 0 ]]; do
    case "$1" in
        --budget) budget="$2"; shift 2 ;;
        --workdir) workdir="$2"; shift 2 ;;
        -h|--help) sed -n '2,16p' "$0"; exit 0 ;;
        *) files+=("$1"); shift ;;
    esac
done

# file -> the tests that cover it (keep the renderer-heavy ones out where a torch-only file
# covers the function; "no tests" in the report names what is left uncovered).
declare -A TESTS=(
    [torchir/samplers/pixel.py]="tests/test_samplers.py tests/test_pixel_sampling.py"
    [torchir/samplers/_pmf.py]="tests/test_samplers.py"
    [torchir/samplers/restir.py]="tests/test_restir_sampler.py"
    [torchir/integrators/restir_di.py]="tests/test_restir.py"
    [torchir/integrators/_light.py]="tests/test_light_samples.py"
    [torchir/integrators/_knn.py]="tests/test_knn_and_watch.py"
    [torchir/integrators/_scene_watch.py]="tests/test_knn_and_watch.py"
    [torchir/modules/loi.py]="tests/test_loi.py"
    [torchir/modules/_blur.py]="tests/test_loi.py"
    [torchir/modules/losses.py]="tests/test_losses.py"
    [torchir/modules/pyramid.py]="tests/test_loi.py"
    [torchir/modules/target_aware.py]="tests/test_denoisers.py"
    [torchir/modules/cross_bilateral.py]="tests/test_denoisers.py"
    [torchir/functions/render.py]="tests/test_render.py"
    [torchir/functions/render_pixels.py]="tests/test_render_pixels.py tests/test_pixel_sampling.py"
    [torchir/functions/probe.py]="tests/test_pixel_sampling.py"
    [torchir/functions/gbuffers.py]="tests/test_gbuffers.py"
    [torchir/training/module.py]="tests/test_training.py tests/test_guards_training.py"
    [torchir/training/parameters.py]="tests/test_training_params.py"
    [torchir/training/results.py]="tests/test_photo_to_answer.py"
    [torchir/training/cli.py]="tests/test_photo_to_answer.py tests/test_training.py"
    [torchir/imageio.py]="tests/test_imageio.py"
    [torchir/derived.py]="tests/test_photo_to_answer.py"
    [torchir/scene.py]="tests/test_scene.py tests/test_render.py tests/test_imageio.py tests/test_photo_to_answer.py"
)
if [[ ${#files[@]} -eq 0 ]]; then
    mapfile -t files < <(printf '%s\n' "${!TESTS[@]}" | sort)
fi

# mutmut forks one child per mutant: a fork of a process whose OpenMP pool is running can
# hang (seen as runs of "timeout"), and the machine is shared. One thread each.
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 DRJIT_NUM_THREADS=1
root="$(cd "$(dirname "$0")/.." && pwd)"
command -v mutmut >/dev/null || { echo "mutmut is not installed: pip install -e '.[mutation]'" >&2; exit 1; }
mkdir -p "$workdir"
report="$workdir/report.md"
printf '# torchir mutation report (%s)\n\n| file | killed | timeout | survived | no tests | not checked | score |\n| --- | --- | --- | --- | --- | --- | --- |\n' "$(date -u +%F)" >"$report"
survivors=""

for file in "${files[@]}"; do
    tests="${TESTS[$file]:-}"
    [[ -n "$tests" ]] || { echo "no test map for $file" >&2; exit 2; }
    name="$(echo "$file" | tr '/.' '__')"
    dir="$workdir/$name"
    if [[ ! -d "$dir" ]]; then  # a fresh copy of the working tree (tracked and untracked files)
        mkdir -p "$dir"
        (cd "$root" && git ls-files -co --exclude-standard | grep -v '\.egg-info/' | tar -cf - -T -) | tar -xf - -C "$dir"
        sed -i '/^\[tool.mutmut\]/,$d' "$dir/pyproject.toml"
        {
            echo "[mutmut]"
            echo "source_paths=torchir"
            echo "only_mutate=$file"
            echo "pytest_add_cli_args_test_selection="
            for t in $tests; do echo "    $t"; done
            printf 'pytest_add_cli_args=\n    -p\n    no:cacheprovider\n    -q\n    -x\n'
        } >"$dir/setup.cfg"
    fi
    echo "== $file ($tests), budget ${budget} min, in $dir"
    (cd "$dir" && timeout "$((budget * 60))" nice -n 15 mutmut run --max-children 1 >run.log 2>&1) || true
    (cd "$dir" && timeout 300 mutmut results --all true >results.txt 2>/dev/null) || true
    count() { grep -c ": $1\$" "$dir/results.txt" || true; }
    k=$(count killed); t=$(count timeout); s=$(count survived); n=$(count "no tests"); u=$(count "not checked")
    score=$(python3 -c "d=$k+$t+$s; print(f'{100*($k+$t)/d:.1f} %' if d else '-')")
    printf '| %s | %s | %s | %s | %s | %s | %s |\n' "$file" "$k" "$t" "$s" "$n" "$u" "$score" >>"$report"
    for m in $(grep ': survived$' "$dir/results.txt" | cut -d: -f1 | tr -d ' '); do
        diff="$(cd "$dir" && timeout 60 mutmut show "$m" 2>/dev/null | grep -E '^[-+][^-+]' || true)"
        survivors+=$'\n'"- \`$m\` (reason: TODO)"$'\n\n```diff\n'"$diff"$'\n```\n'
    done
done
printf '\n## Survivors\n%s\n' "${survivors:-none}" >>"$report"
cat "$report"
