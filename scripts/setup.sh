#!/usr/bin/env bash
# Installs what drape needs on a fresh Debian machine; safe to run again.
#   scripts/setup.sh            Vulkan loader, lavapipe, validation layers
#   scripts/setup.sh --shaders  also the pinned nightly that rebuilds the SPIR-V
set -euo pipefail

SHADER_TOOLCHAIN=nightly-2026-08-15   # keep in step with tools/shader-builder/rust-toolchain.toml
# xvfb, x11-apps (xwd) and libxkbcommon-x11-0 (winit's keyboard on X11): `drape view` and its test.
# ffmpeg (ffprobe too): `drape prepare` decodes the user's videos with it.
packages=(libvulkan1 mesa-vulkan-drivers vulkan-validationlayers xvfb x11-apps libxkbcommon-x11-0 ffmpeg)

missing=()
for pkg in "${packages[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if ((${#missing[@]})); then
    sudo=""
    [ "$(id -u)" -ne 0 ] && sudo="sudo"
    echo "setup: installing ${missing[*]}"
    $sudo apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}" >/dev/null
fi

if [ "${1:-}" = "--shaders" ]; then
    if ! rustup toolchain list | grep -q "^$SHADER_TOOLCHAIN"; then
        echo "setup: installing $SHADER_TOOLCHAIN for the shader builder (about 1.6 GB)"
    fi
    # Also adds missing components to an existing install.
    rustup toolchain install "$SHADER_TOOLCHAIN" --profile minimal -c rust-src -c rustc-dev -c llvm-tools >/dev/null
fi
