#!/usr/bin/env bash
# Runs every test: installs what is missing, then `cargo test` on Mesa lavapipe with the Khronos
# validation layers on (a validation warning or error fails the test that caused it).
# Set CAO_XR_TEST_DEVICE=native to test on the machine's own GPU driver instead.
set -euo pipefail
cd "$(dirname "$0")/.."
# The desktop-window test runs under Xvfb; the DICOM tests write their series with dcmtk and
# read the real sample files pydicom ships; tests/integration/foreign.rs checks volumes nobody here wrote
# against niftilib (nifti-bin), dcm2niix and teem (teem-apps); tests/integration/labels.rs reads
# label maps nibabel wrote, on grids of their own, as nibabel reads them, and DICOM SEG objects
# and 3D Slicer segmentations that highdicom and pynrrd wrote (pip-installed into private
# environments: python3-venv) as those read them.
CAO_XR_EXTRA_PACKAGES="xvfb xauth dcmtk python3-pydicom nifti-bin dcm2niix teem-apps python3-nibabel python3-numpy python3-venv" source scripts/setup.sh
export CAO_XR_REQUIRE_XVFB=1
export CAO_XR_REQUIRE_DCMTK=1
export CAO_XR_REQUIRE_PYDICOM=1
export CAO_XR_REQUIRE_NIBABEL=1
# DICOM SEG objects written by highdicom and .seg.nrrd files written by pynrrd, each installed
# with pip into a private environment.
export CAO_XR_REQUIRE_HIGHDICOM=1
export CAO_XR_REQUIRE_PYNRRD=1
# nibabel's and mricron's NIfTI files (downloaded once, cached) and the CT head (fetched by the
# test itself when it is not cached yet): required, so a failed download fails CI.
export CAO_XR_FOREIGN_DATA="${CAO_XR_FOREIGN_DATA:-$HOME/.cache/cao-xr/foreign}"
scripts/foreign-data.sh "$CAO_XR_FOREIGN_DATA"
export CAO_XR_REQUIRE_FOREIGN=1
if [ "${CAO_XR_TEST_DEVICE:-lavapipe}" = "lavapipe" ]; then
  [ -n "$LVP_ICD" ] || { echo "lavapipe (mesa-vulkan-drivers) is not installed" >&2; exit 1; }
  export VK_DRIVER_FILES="$LVP_ICD"
fi
export CAO_XR_VALIDATION=1
# The lint gate (Cargo.toml [lints]): formatting and clippy, warnings as errors. A minimal
# rustup install has neither tool: add them.
if command -v rustup >/dev/null 2>&1; then
  for c in clippy rustfmt; do
    rustup component list --installed 2>/dev/null | grep -q "^$c" || rustup component add "$c"
  done
fi
cargo fmt --check
cargo clippy --all-targets -- -D warnings
# The API docs build without a broken link.
RUSTDOCFLAGS="-D warnings" cargo doc --no-deps --lib
# The OpenXR test (tests/integration/xr.rs) runs against Monado in a Debian trixie root, built once and
# cached (scripts/xr-root.sh); without it that test fails with the reason rather than skipping.
scripts/xr-root.sh >/dev/null || echo "test.sh: the Monado test root could not be built; tests/integration/xr.rs will fail" >&2
export CAO_XR_REQUIRE_XR=1
if [ $# -eq 0 ]; then
  # The soak judges its own CPU time per frame for a trend, so it runs alone, after the rest:
  # on two cores a neighbour (the Monado tests) once added 43 % to its late tenths.
  cargo test -- --skip soak::
  cargo test --test integration -- soak::
else
  cargo test "$@"
fi
