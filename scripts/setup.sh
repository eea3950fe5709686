#!/usr/bin/env bash
# Installs what cao-xr needs on Debian 12 (run as root, or with sudo available): the Vulkan loader,
# Mesa's lavapipe CPU driver, the Khronos validation layers and glslc; and checks for Rust.
# Sourced by run.sh and test.sh; safe to run again (it only installs what is missing).
set -euo pipefail
# debian_mirror: the Debian archive this machine's apt uses (for xr-root.sh's trixie root).
source "$(dirname "${BASH_SOURCE[0]}")/apt-mirror.sh"

need=()
have_pkg() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q "install ok installed"; }
# The X11 libraries are what winit loads at run time for the desktop window.
for p in libvulkan1 mesa-vulkan-drivers vulkan-validationlayers glslc \
  libx11-6 libx11-xcb1 libxkbcommon-x11-0 libxcursor1 libxrandr2 libxi6 ${CAO_XR_EXTRA_PACKAGES:-}; do
  have_pkg "$p" || need+=("$p")
done
if [ ${#need[@]} -gt 0 ]; then
  echo "cao-xr setup: installing ${need[*]}" >&2
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need[@]}" >/dev/null
fi

if ! command -v cargo >/dev/null 2>&1; then
  if [ -x "$HOME/.cargo/bin/cargo" ]; then
    export PATH="$HOME/.cargo/bin:$PATH"
  else
    echo "cao-xr setup: Rust is missing; installing it with rustup (https://rustup.rs)" >&2
    curl -sSf https://sh.rustup.rs | sh -s -- -y --profile minimal
    export PATH="$HOME/.cargo/bin:$PATH"
  fi
fi

# Mesa's lavapipe (the CPU Vulkan driver used for tests and machines without a GPU).
LVP_ICD=$(ls /usr/share/vulkan/icd.d/lvp_icd.*.json 2>/dev/null | head -n1 || true)
export LVP_ICD
