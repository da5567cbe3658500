#!/usr/bin/env bash
# Sets up the environments, then runs blender_tests/ with .venv (Python 3.11, bpy 5.0, numpy 1.26) and,
# where it exists, .venv313 (Python 3.13, bpy 5.2, numpy 2). Extra arguments go to pytest, e.g.
#   bash scripts/test.sh -k package -x
set -uo pipefail
cd "$(dirname "$0")/.."

bash scripts/setup.sh || { echo "test: FAILED (scripts/setup.sh)"; exit 1; }

export PYTHONDONTWRITEBYTECODE=1  # tests must not write into the repo
summary=()
failed=0
for venv in .venv .venv313; do
    if [[ ! -x $venv/bin/python ]]; then
        [[ $venv == .venv ]] && { echo "test: FAILED (.venv missing after setup)"; exit 1; }
        summary+=("$venv: not present, skipped"); continue
    fi
    version=$("$venv/bin/python" -c "import sys, numpy; print(f'Python {sys.version.split()[0]}, numpy {numpy.__version__}')")
    # The pure core first, with bpy made unimportable (it must not need Blender), then the Blender layer.
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
    if [[ $status -eq 0 ]]; then
        summary+=("$venv ($version): passed")
    else
        summary+=("$venv ($version): FAILED (pytest exit $status)"); failed=1
    fi
done

printf 'test: %s\n' "${summary[@]}"
if [[ $failed -ne 0 ]]; then echo "test: FAILED"; exit 1; fi
echo "test: all passed"
