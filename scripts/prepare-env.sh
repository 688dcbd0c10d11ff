#!/usr/bin/env bash
# The Python environment `drape prepare` runs its one model in: mediapipe's legacy Pose
# (33 landmarks and a person mask; tools/drape/python/landmarks.py). mediapipe 0.10.21
# is the last wheel that ships the legacy Pose models inside it (later ones, and
# model_complexity 0 and 2, download them at run time, which drape must not do), and
# it is built for CPython 3.11 only, hence python3.11.
# Everything is installed with --no-deps at exact versions: mediapipe's declared
# dependencies (jax, jaxlib, opencv-contrib-python, sentencepiece, sounddevice) are
# not used by the legacy solutions and would triple the size; matplotlib is imported
# by mediapipe.solutions.drawing_utils, so it and its own dependencies are listed.
# At target/prepare-venv, or at $DRAPE_PREPARE_VENV when set (an installed drape puts
# it under ${XDG_CACHE_HOME:-$HOME/.cache}/drape/prepare-venv). Made once (measured:
# about 27 s, 412 MB) and reused: a stamp records what was installed.
# Prints the environment's python as its last line on stdout:
#   PY=$(scripts/prepare-env.sh | tail -1)
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
venv="${DRAPE_PREPARE_VENV:-$root/target/prepare-venv}"
py="$venv/bin/python"
requirements="mediapipe==0.10.21 absl-py==2.5.1 attrs==26.1.0 flatbuffers==25.12.19 \
numpy==1.26.4 protobuf==4.25.9 opencv-python-headless==4.10.0.84 matplotlib==3.11.2 \
contourpy==1.3.3 cycler==0.12.1 fonttools==4.68.0 kiwisolver==1.5.1 packaging==26.4 \
pillow==13.0.0 pyparsing==3.3.3 python-dateutil==4.0.0 tzdata==2026.6"
stamp="$venv/.drape-stamp"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$requirements" ] && [ -x "$py" ]; then
    echo "prepare-env: ready at $py" >&2
    echo "$py"
    exit 0
fi
if ! command -v python3.11 >/dev/null 2>&1 || ! python3.11 -c "import venv" >/dev/null 2>&1; then
    echo "error: python3.11 (with its venv module) is needed for mediapipe 0.10.21; install it (Debian/Ubuntu: apt-get install python3.11 python3.11-venv, or pyenv install 3.11)" >&2
    exit 1
fi
start=$SECONDS
rm -rf "$venv"
mkdir -p "$(dirname "$venv")"
python3.11 -m venv "$venv"
"$py" -m pip install -q --disable-pip-version-check --no-cache-dir --no-deps $requirements >&2
"$py" -c "import mediapipe as mp; mp.solutions.pose.Pose(model_complexity=1, enable_segmentation=True).close()" >&2
echo "$requirements" > "$stamp"
echo "prepare-env: mediapipe ready at $py ($((SECONDS - start)) s)" >&2
echo "$py"
