#!/usr/bin/env bash
# Builds, once, the Debian trixie root the OpenXR test runs in (Monado is packaged in trixie, not
# in bookworm; a binary built on bookworm runs unchanged inside it). Cached at $CAO_XR_XR_ROOT
# (default /var/cache/cao-xr/trixie-root); a root whose marker .cao-xr-ready lists the same
# packages is reused.
# Needs root and Debian's archive: $CAO_XR_DEBIAN_MIRROR, else the mirror this machine's own apt
# sources name (debian_mirror in scripts/apt-mirror.sh). Prints the root's path.
set -euo pipefail
source "$(dirname "$0")/apt-mirror.sh"
ROOT="${CAO_XR_XR_ROOT:-/var/cache/cao-xr/trixie-root}"
# The runtime (monado-service + its OpenXR runtime library), the Khronos loader, the OpenXR core
# validation layer, lavapipe, the Vulkan loader and the Khronos validation layers; the X11 libraries
# winit loads for `cao-xr xr --mirror`.
PACKAGES="monado-service,libopenxr1-monado,libopenxr-loader1,openxr-layer-corevalidation,mesa-vulkan-drivers,libvulkan1,vulkan-validationlayers,ca-certificates,libx11-6,libx11-xcb1,libxkbcommon-x11-0,libxcursor1,libxrandr2,libxi6"
# The marker holds the package list, so a root built from an older list is rebuilt.
if [ "$(cat "$ROOT/.cao-xr-ready" 2>/dev/null)" = "$PACKAGES" ]; then echo "$ROOT"; exit 0; fi
[ "$(id -u)" -eq 0 ] || { echo "xr-root: building the trixie root needs root" >&2; exit 1; }
MIRROR=$(debian_mirror) || { echo "xr-root: cannot build the trixie root without a Debian mirror" >&2; exit 1; }
echo "xr-root: Debian mirror $MIRROR" >&2
if ! command -v mmdebstrap >/dev/null 2>&1; then
  echo "xr-root: installing mmdebstrap" >&2
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq mmdebstrap >/dev/null
fi
rm -rf "$ROOT.tmp"
mkdir -p "$(dirname "$ROOT")"
echo "xr-root: building $ROOT (Debian trixie + Monado); this runs once" >&2
start=$(date +%s)
# --variant=apt keeps the root small: only Essential + apt + what the packages pull in.
mmdebstrap --variant=apt --include="$PACKAGES" --skip=check/empty \
  trixie "$ROOT.tmp" "$MIRROR" >&2
rm -rf "$ROOT"
mv "$ROOT.tmp" "$ROOT"
echo "$PACKAGES" > "$ROOT/.cao-xr-ready"
echo "xr-root: built in $(( $(date +%s) - start )) s" >&2
echo "$ROOT"
