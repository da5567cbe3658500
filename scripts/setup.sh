#!/usr/bin/env bash
# Sets up ExClone's development environments. Idempotent: a second run only checks stamps.
#   .venv     Python 3.11 + bpy 5.0.1 + numpy 1.26 (requirements.txt)      -- always
#   .venv313  Python 3.13 + bpy 5.2.x + numpy 2   (requirements-py313.txt) -- where Python 3.13 exists
# and extracts the face detector and landmark models from the mediapipe wheel into exclone_addon/models/.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD

find_python() {  # $1 = minor version, e.g. 3.11; prints a python of that version or nothing
    local v=$1 cand
    for cand in "python$v" "$(pyenv root 2>/dev/null)/versions/$v"*/bin/"python$v" python3; do
        if command -v "$cand" >/dev/null 2>&1 && "$cand" -c "import sys; sys.exit(sys.version_info[:2] != tuple(map(int, '$v'.split('.'))))" 2>/dev/null; then
            command -v "$cand"; return
        fi
    done
}

# This machine's pip.conf adds file:// indexes that hold only a few projects; pip warns once per other
# project ("Location ... is ignored"). Drop just those lines.
pip_run() {  # $1 = python, the rest = pip arguments
    local py=$1; shift
    "$py" -m pip --disable-pip-version-check "$@" 2> >(grep -v "is ignored: it is neither a file nor a directory" >&2)
}

make_venv() {  # $1 = venv dir, $2 = python, $3 = requirements file
    local venv=$1 py=$2 req=$3 stamp="$1/.requirements.sha256"
    local want; want=$(sha256sum "$req" | cut -d' ' -f1)
    if [[ -f "$stamp" && "$(cat "$stamp")" == "$want" ]]; then
        echo "setup: $venv is up to date ($req)"; return
    fi
    echo "setup: creating $venv from $req with $py"
    rm -rf "$venv"
    "$py" -m venv "$venv"
    pip_run "$venv/bin/python" install --quiet --upgrade pip
    # One pip command with every pin, so that pip never upgrades numpy under bpy.
    pip_run "$venv/bin/python" install --quiet -r "$req"
    echo "$want" > "$stamp"
}

PY311=$(find_python 3.11)
[[ -n "$PY311" ]] || { echo "setup: Python 3.11 is required (bpy 5.0.1 is built for it)" >&2; exit 1; }
make_venv .venv "$PY311" requirements.txt

PY313=$(find_python 3.13)
if [[ -n "$PY313" ]]; then
    make_venv .venv313 "$PY313" requirements-py313.txt
else
    echo "setup: no Python 3.13 here; skipping the numpy 2 environment"
fi

# Face detector + landmark models (Apache-2.0), taken from the mediapipe wheel: no mediapipe import at
# run time and no network after setup.
MODELS=exclone_addon/models
if [[ ! -f $MODELS/face_landmark.tflite || ! -f $MODELS/face_detection_short_range.tflite
      || ! -f $MODELS/iris_landmark.tflite ]]; then
    mkdir -p .cache/wheels
    ls .cache/wheels/mediapipe-0.10.21-*.whl >/dev/null 2>&1 || \
        pip_run .venv/bin/python download --quiet --no-deps \
            -d .cache/wheels mediapipe==0.10.21
    .venv/bin/python scripts/extract_models.py .cache/wheels/mediapipe-0.10.21-*.whl "$MODELS"
fi
echo "setup: done"
