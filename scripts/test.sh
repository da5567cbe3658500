#!/usr/bin/env bash
# Sets up the environments, then runs blender_tests/ with .venv (Python 3.11, bpy 5.0, numpy 1.26) and,
# where it exists, .venv313 (Python 3.13, bpy 5.2, numpy 2). Extra arguments go to pytest, e.g.
#   bash scripts/test.sh -k package -x
# The two environments run at the same time, one BLAS thread each (two runs on two cores: the
# suite's wall time about halves), each into its own log, printed whole when both are done.
set -uo pipefail
cd "$(dirname "$0")/.."

bash scripts/setup.sh || { echo "test: FAILED (scripts/setup.sh)"; exit 1; }
[[ -x .venv/bin/python ]] || { echo "test: FAILED (.venv missing after setup)"; exit 1; }

export PYTHONDONTWRITEBYTECODE=1  # tests must not write into the repo
logs=$(mktemp -d)
trap 'rm -rf "$logs"' EXIT

# One environment's run: the pure core first, with bpy made unimportable (it must not need
# Blender), then the Blender layer; its summary line goes to $logs/<venv>.summary.
run_venv() {
    local venv=$1; shift
    local version core_status blender_status status
    version=$("$venv/bin/python" -c "import sys, numpy; print(f'Python {sys.version.split()[0]}, numpy {numpy.__version__}')")
    echo "test: pytest blender_tests/core without bpy, with $venv ($version)"
    EXCLONE_WITHOUT_BPY=1 "$venv/bin/python" -m pytest blender_tests/core "$@"
    core_status=$?
    echo "test: pytest blender_tests/blender with $venv ($version)"
    "$venv/bin/python" -m pytest blender_tests/blender "$@"
    blender_status=$?
    # pytest's 5 = no tests collected: fine for one half (-k may select none there), not for both
    if [[ $core_status -eq 5 && $blender_status -eq 5 ]]; then status=5
    elif [[ $core_status -ne 0 && $core_status -ne 5 ]]; then status=$core_status
    elif [[ $blender_status -ne 0 && $blender_status -ne 5 ]]; then status=$blender_status
    else status=0; fi
    if [[ $status -eq 0 ]]; then echo "$venv ($version): passed" > "$logs/$venv.summary"
    else echo "$venv ($version): FAILED (pytest exit $status)" > "$logs/$venv.summary"; fi
}

venvs=()
for venv in .venv .venv313; do
    if [[ -x $venv/bin/python ]]; then
        venvs+=("$venv")
        echo "test: $venv started (log printed when it ends)"
        OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 \
            run_venv "$venv" "$@" > "$logs/$venv.log" 2>&1 &
    else
        echo "$venv: not present, skipped" > "$logs/$venv.summary"
    fi
done
wait

failed=0
for venv in "${venvs[@]}"; do
    echo "================================ $venv ================================"
    cat "$logs/$venv.log"
done
for venv in .venv .venv313; do
    [[ -f $logs/$venv.summary ]] || echo "$venv: FAILED (its run ended without a summary)" > "$logs/$venv.summary"
    echo "test: $(cat "$logs/$venv.summary")"
    grep -q "FAILED" "$logs/$venv.summary" && failed=1
done
if [[ $failed -ne 0 ]]; then echo "test: FAILED"; exit 1; fi
echo "test: all passed"
