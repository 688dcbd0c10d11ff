#!/usr/bin/env bash
# Real calibrated multi-view footage for `drape prepare`'s tests, fetched at test time
# (not vendored): the PyPI wheel pose2sim==0.10.49 (BSD-3-Clause, 51 MB) ships
# Pose2Sim/Demo_SinglePerson and Demo_MultiPerson: four synchronised views
# (videos/cam01..04.mp4, 100 frames at 60 fps) with a Qualisys calibration
# (calibration/Calib.qca.txt) and the demo's Config.toml; Demo_SinglePerson also has
# the calibration's own checkerboard (intrinsics/) and scene (extrinsics/) images.
# The wheel holds no reference 2D/3D pose output.
# Downloaded once into target/pose2sim/ (checked against its sha256) and extracted
# there: both demos, the licence (and the rest of the wheel's dist-info, which
# importlib.metadata needs), and the three Pose2Sim modules scripts/qca-reference.py
# imports the reference conversion from. Reruns with the same stamp do nothing.
# Prints the extracted root as its last line on stdout; the footage is then at
#   "$ROOT/Pose2Sim/Demo_SinglePerson", the licence at "$ROOT/LICENSE".
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
dir="$root/target/pose2sim"
out="$dir/extracted"
wheel="$dir/pose2sim-0.10.49-py3-none-any.whl"
sha256="403e0dc4065898ba6a595e72a8970950310979253d60e24c2e00b16b36bf21e1"
stamp="$out/.drape-stamp"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$sha256" ]; then
    echo "pose2sim-footage: ready at $out" >&2
    echo "$out"
    exit 0
fi
mkdir -p "$dir"
if ! echo "$sha256  $wheel" | sha256sum --check --status 2>/dev/null; then
    rm -f "$wheel"
    python3 -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: \
        pose2sim==0.10.49 -d "$dir" >&2
    echo "$sha256  $wheel" | sha256sum --check --quiet >&2
fi
rm -rf "$out"
mkdir -p "$out"
# unzip's wildcards cross '/', so Demo_X/* is the whole demo tree.
unzip -q "$wheel" -d "$out" 'Pose2Sim/Demo_SinglePerson/*' 'Pose2Sim/Demo_MultiPerson/*' \
    'pose2sim-0.10.49.dist-info/*' Pose2Sim/__init__.py Pose2Sim/calibration.py Pose2Sim/common.py
cp "$out/pose2sim-0.10.49.dist-info/licenses/LICENSE" "$out/LICENSE"
echo "$sha256" > "$stamp"
echo "pose2sim-footage: pose2sim 0.10.49 demos extracted at $out" >&2
echo "$out"
