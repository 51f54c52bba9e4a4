#!/usr/bin/env bash
# Mutation testing of torchir's numerical cores with mutmut (pip install -e '.[mutation]').
# Not run in CI: it is slow. Usage:
#
#   scripts/mutation.sh [--budget MINUTES] [--workdir DIR] [--tests "TEST ..."] [--sample N] [FILE ...]
#
# FILE: modules under torchir/ to mutate (default: every file of the map below). Each file is
# mutated in its own copy of the tree, DIR/<name>/ (default /tmp/torchir-mutation), against
# only the test files that cover it, under `nice -n 15`, one child process. Re-running the
# same command resumes: mutmut keeps each mutant's result in DIR/<name>/mutants/ and skips
# the ones already tested (delete DIR/<name> after changing the code or its tests). The
# budget (default 30 min) is per file; what it leaves unchecked shows as "not checked".
# The report, DIR/report.md, gives per file: mutants, killed, timeout, survived, no tests, not
# checked and the score killed+timeout / (killed+timeout+survived); then each survivor's diff, to be
# annotated (caught now / equivalent mutant / accepted, why). --tests overrides the map's test
# files for every FILE given (e.g. to try a new fast test file before it enters the map).
# --sample N tests only a fixed random sample (seed 0) of N of each file's mutants, for files
# whose tests render and so cannot test every mutant within a budget: the mutants are
# generated first (a `mutmut run` filtered to no mutant: generation and the test-coverage
# pass), the sample is drawn from `mutmut results --all true` and kept in DIR/<name>/sample.txt,
# and only its mutants not yet tested are run (`mutmut run NAME ...`; it re-runs every mutant
# it is named, so a resumed run leaves out the ones already done). The report's counts are then
# those of the sample, and the score comes with its 95 % Wilson interval.
set -euo pipefail

budget=30
workdir=/tmp/torchir-mutation
files=()
tests_override=""
sample=0
while [[ $# -gt 0 ]]; do
    case "$1" in
        --budget) budget="$2"; shift 2 ;;
        --workdir) workdir="$2"; shift 2 ;;
        --tests) tests_override="$2"; shift 2 ;;
        --sample) sample="$2"; shift 2 ;;
        -h|--help) sed -n '2,25p' "$0"; exit 0 ;;
        *) files+=("$1"); shift ;;
    esac
done

# file -> the tests that cover it (keep the renderer-heavy ones out where a torch-only file
# covers the function; "no tests" in the report names what is left uncovered).
declare -A TESTS=(
    [torchir/samplers/pixel.py]="tests/samplers/test_samplers.py tests/samplers/test_pixel_sampling.py"
    [torchir/samplers/_pmf.py]="tests/samplers/test_samplers.py"
    [torchir/samplers/restir.py]="tests/samplers/test_restir_sampler.py"
    [torchir/integrators/restir_di.py]="tests/integrators/test_restir_integrator.py"
    [torchir/integrators/_restir_pass.py]="tests/integrators/test_restir_integrator.py"
    [torchir/integrators/_restir_state.py]="tests/integrators/test_restir_integrator.py"
    [torchir/integrators/restir_options.py]="tests/integrators/test_restir_options.py"
    [torchir/integrators/_light.py]="tests/integrators/test_light_samples.py"
    [torchir/integrators/_knn.py]="tests/integrators/test_knn_and_watch.py"
    [torchir/integrators/_scene_watch.py]="tests/integrators/test_knn_and_watch.py"
    [torchir/modules/loi.py]="tests/modules/test_loi.py"
    [torchir/modules/_loi_config.py]="tests/modules/test_loi.py"
    [torchir/modules/_loi_terms.py]="tests/modules/test_loi.py tests/modules/test_loi_native.py"
    [torchir/modules/_blur.py]="tests/modules/test_loi.py"
    [torchir/modules/losses.py]="tests/modules/test_losses.py"
    [torchir/modules/pyramid.py]="tests/modules/test_loi.py"
    [torchir/modules/target_aware.py]="tests/modules/test_denoisers.py"
    [torchir/modules/cross_bilateral.py]="tests/modules/test_denoisers.py"
    [torchir/modules/_windows.py]="tests/modules/test_denoisers.py"
    [torchir/functions/_args.py]="tests/functions/test_functions_core.py tests/functions/test_functions_pixels.py"
    [torchir/functions/_bound_op.py]="tests/functions/test_functions_core.py tests/functions/test_functions_pixels.py"
    [torchir/functions/_passes.py]="tests/functions/test_functions_core.py tests/functions/test_functions_pixels.py"
    [torchir/functions/_sampler_op.py]="tests/functions/test_functions_core.py tests/functions/test_functions_pixels.py"
    [torchir/functions/render.py]="tests/functions/test_functions_core.py tests/functions/test_functions_pixels.py"
    [torchir/functions/render_pixels.py]="tests/functions/test_functions_core.py tests/functions/test_functions_pixels.py"
    [torchir/functions/probe.py]="tests/functions/test_functions_core.py tests/functions/test_functions_pixels.py"
    [torchir/functions/gbuffers.py]="tests/functions/test_functions_core.py tests/functions/test_functions_pixels.py"
    [torchir/training/module.py]="tests/training/test_training_module.py"
    [torchir/training/_resolve.py]="tests/training/test_training_module.py"
    [torchir/training/parameters.py]="tests/training/test_training_params.py"
    [torchir/training/results.py]="tests/training/test_training_results.py tests/training/test_photo_to_answer.py"
    [torchir/training/cli.py]="tests/training/test_training_cli.py tests/training/test_photo_to_answer.py tests/training/test_training.py"
    [torchir/training/data.py]="tests/training/test_training_data.py"
    [torchir/training/callbacks.py]="tests/training/test_training_callbacks.py"
    [torchir/imageio.py]="tests/core/test_imageio.py"
    [torchir/derived.py]="tests/training/test_photo_to_answer.py"
    [torchir/_scene_values.py]="tests/core/test_scene.py"
    [torchir/_scene_loading.py]="tests/core/test_scene.py tests/training/test_photo_to_answer.py"
    [torchir/welding.py]="tests/core/test_welding.py"
    [torchir/scene.py]="tests/core/test_scene.py tests/functions/test_render.py tests/core/test_imageio.py tests/training/test_photo_to_answer.py"
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
printf '# torchir mutation report (%s)\n\n| file | mutants | killed | timeout | survived | no tests | not checked | score |\n| --- | --- | --- | --- | --- | --- | --- | --- |\n' "$(date -u +%F)" >"$report"
survivors=""

for file in "${files[@]}"; do
    tests="${tests_override:-${TESTS[$file]:-}}"
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
    start=$SECONDS
    if grep -q "dr.CustomOp\|(BoundRenderOp)" "$root/$file"; then
        # Dr.Jit custom ops: generate the mutants first, then give eval back its signature
        (cd "$dir" && timeout "$((budget * 60))" nice -n 15 mutmut run --max-children 1 'no-mutant-is-named-this' >generate.log 2>&1) || true
        python3 "$root/scripts/mutmut_eval_shim.py" "$dir" "$file"
    fi
    if [[ "$sample" -gt 0 ]]; then
        # generate (and map tests to functions) without testing a mutant: the filter matches none
        (cd "$dir" && timeout "$((budget * 60))" nice -n 15 mutmut run --max-children 1 'no-mutant-is-named-this' >generate.log 2>&1) || true
        (cd "$dir" && timeout 300 mutmut results --all true >results.txt 2>/dev/null) || true
        python3 - "$dir/results.txt" "$sample" >"$dir/sample.txt" <<'PY'
import random, sys
names = sorted(line.split(":")[0].strip() for line in open(sys.argv[1]) if ": " in line)
for name in sorted(random.Random(0).sample(names, min(int(sys.argv[2]), len(names)))):
    print(name)
PY
        total=$(grep -c ': ' "$dir/results.txt" || true)
        sed 's/.*/ &:/' "$dir/sample.txt" >"$dir/sample.pat"  # " name:" matches that mutant only
        mapfile -t pending < <(grep -F -f "$dir/sample.pat" "$dir/results.txt" | grep ': not checked$' | cut -d: -f1 | tr -d ' ')
        left=$((budget * 60 - (SECONDS - start)))
        if [[ ${#pending[@]} -gt 0 && $left -gt 0 ]]; then
            (cd "$dir" && timeout "$left" nice -n 15 mutmut run --max-children 1 "${pending[@]}" >run.log 2>&1) || true
        fi
        (cd "$dir" && timeout 300 mutmut results --all true 2>/dev/null | grep -F -f sample.pat >results.txt) || true
        mutants="$(wc -l <"$dir/sample.txt") of $total (sample, seed 0)"
    else
        (cd "$dir" && timeout "$((budget * 60))" nice -n 15 mutmut run --max-children 1 >run.log 2>&1) || true
        (cd "$dir" && timeout 300 mutmut results --all true >results.txt 2>/dev/null) || true
        mutants=$(grep -c ': ' "$dir/results.txt" || true)
    fi
    count() { grep -c ": $1\$" "$dir/results.txt" || true; }
    k=$(count killed); t=$(count timeout); s=$(count survived); n=$(count "no tests"); u=$(count "not checked")
    score=$(python3 -c "
import math
k, d = $k + $t, $k + $t + $s
if not d:
    print('-')
elif $sample > 0:  # Wilson score interval of a binomial proportion, z = 1.96
    p, z = k / d, 1.96
    c, h = (p + z * z / (2 * d)) / (1 + z * z / d), z * math.sqrt(p * (1 - p) / d + z * z / (4 * d * d)) / (1 + z * z / d)
    print(f'{100 * p:.1f} % (95 % CI {100 * (c - h):.1f}-{100 * (c + h):.1f} %)')
else:
    print(f'{100 * k / d:.1f} %')")
    printf '| %s | %s | %s | %s | %s | %s | %s | %s |\n' "$file" "$mutants" "$k" "$t" "$s" "$n" "$u" "$score" >>"$report"
    for m in $(grep ': survived$' "$dir/results.txt" | cut -d: -f1 | tr -d ' '); do
        diff="$(cd "$dir" && timeout 60 mutmut show "$m" 2>/dev/null | grep -E '^[-+][^-+]' || true)"
        survivors+=$'\n'"- \`$m\` (reason: TODO)"$'\n\n```diff\n'"$diff"$'\n```\n'
    done
done
printf '\n## Survivors\n%s\n' "${survivors:-none}" >>"$report"
cat "$report"
