#!/usr/bin/env bash
# The PyTorch (CPU) reference the tests compare the neural ops against: a virtual
# environment at target/torch-venv with pinned torch, numpy, pytorch-msssim, and the
# lpips package with torchvision and safetensors (LPIPS and its weights converter), and
# gsplat (its pure-PyTorch projection, SH and tile binning are the splatter's reference;
# its CUDA kernels are compiled only when called, which the tests never do), and
# scikit-image (the PSNR and SSIM references of the evaluation metrics), OpenCV
# (lens distortion's reference) and Pillow (JPEG fixtures the image crate cannot write:
# CMYK). The
# torch package from PyPI brings its CUDA libraries (about 5 GB; the venv is ~7 GB);
# it runs on the CPU. Made once (about 2 minutes) and reused: a stamp file records
# what was installed, and a rerun with the same stamp does nothing.
# Prints the environment's python as its last line on stdout:
#   PY=$(scripts/torch-env.sh | tail -1)
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
venv="$root/target/torch-venv"
py="$venv/bin/python"
base="torch==2.9.1 numpy==2.1.3 pytorch-msssim==1.0.0"
extra="torchvision==0.24.1 lpips==0.1.4 safetensors==0.6.2 packaging==25.0 gsplat==1.5.3 jaxtyping==0.3.11 rich==15.0.0 ninja==1.13.2 scikit-image==0.25.2 opencv-python-headless==4.12.0.88 pillow==13.0.0"
requirements="$base $extra"
stamp="$venv/.drape-stamp"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$requirements" ] && [ -x "$py" ]; then
    echo "torch-env: ready at $py" >&2
    echo "$py"
    exit 0
fi
start=$SECONDS
if [ -f "$stamp" ] && [[ "$(cat "$stamp")" == "$base"* ]] && [ -x "$py" ]; then
    # The same torch with other small packages: add what is missing (pip keeps the rest).
    echo "torch-env: adding $extra to $venv" >&2
else
    echo "torch-env: installing $requirements into $venv (once; about 5 GB to download)" >&2
    rm -rf "$venv"
    python3 -m venv "$venv"
fi
# No cache: the wheels would double the disk used, and the venv itself is the cache.
"$py" -m pip install -q --disable-pip-version-check --no-cache-dir $requirements >&2
"$py" -c "import torch, numpy, pytorch_msssim, torchvision, lpips, safetensors, packaging, gsplat, skimage.metrics, cv2, PIL; from gsplat.cuda._torch_impl import _fully_fused_projection; lpips.LPIPS(net='alex', pretrained=True, pnet_rand=True, verbose=False)" >&2
echo "$requirements" > "$stamp"
echo "torch-env: installed in $((SECONDS - start)) s ($(du -sh "$venv" | cut -f1))" >&2
echo "torch-env: ready at $py" >&2
echo "$py"
