#!/usr/bin/env bash
# The PyTorch (CPU) reference the tests compare the neural ops against: a virtual
# environment at target/torch-venv with pinned torch, numpy and pytorch-msssim. The
# package from PyPI brings its CUDA libraries (about 5 GB); it runs on the CPU. Made
# once and reused: a stamp file records what was installed.
# Prints the environment's python as its last line on stdout.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
venv="$root/target/torch-venv"
requirements="torch==2.9.1 numpy==2.1.3 pytorch-msssim==1.0.0"
stamp="$venv/.drape-stamp"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$requirements" ] && [ -x "$venv/bin/python" ]; then
    echo "$venv/bin/python"
    exit 0
fi
echo "torch-env: installing $requirements into $venv (once; about 5 GB)" >&2
rm -rf "$venv"
python3 -m venv "$venv"
"$venv/bin/python" -m pip install -q --disable-pip-version-check $requirements >&2
"$venv/bin/python" -c "import torch, numpy, pytorch_msssim" >&2
echo "$requirements" > "$stamp"
echo "torch-env: ready" >&2
echo "$venv/bin/python"
