#!/usr/bin/env bash
# A second Python environment for the clients the PyTorch one cannot hold: numpy 1.x
# (ZJU-MoCap annotations pickled as numpy 1.x writes them: protocol 3 from np.save,
# 1.x's module paths) and kubernetes-validate (the cluster manifest, checked offline).
# At target/clients-venv, made once (a few seconds; a stamp records what was installed)
# and reused. Prints the environment's python as its last line on stdout.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
venv="$root/target/clients-venv"
py="$venv/bin/python"
requirements="numpy==1.26.4 kubernetes-validate==1.37.0"
stamp="$venv/.drape-stamp"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$requirements" ] && [ -x "$py" ]; then
    echo "$py"
    exit 0
fi
rm -rf "$venv"
python3 -m venv "$venv"
"$py" -m pip install -q --disable-pip-version-check --no-cache-dir $requirements >&2
"$py" -c "import numpy, kubernetes_validate; assert numpy.__version__.startswith('1.')" >&2
echo "$requirements" > "$stamp"
echo "clients-env: numpy 1.x and kubernetes-validate ready at $py" >&2
echo "$py"
