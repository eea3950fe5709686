#!/usr/bin/env bash
# Fetches volumes that nobody on this project wrote, for tests/integration/foreign.rs, into DIR (default
# $CAO_XR_FOREIGN_DATA, else ~/.cache/cao-xr/foreign): nibabel's NIfTI test files (Debian's
# python3-nibabel, unpacked only: it is not installed), the Colin27 MRI template that mricron
# ships (mricron-data) and ITK's example volumes (insighttoolkit5-examples). Downloaded from
# Debian's archive with `apt-get download`, never committed. Cached: once every file is there, a
# second run does nothing.
set -euo pipefail
dest="${1:-${CAO_XR_FOREIGN_DATA:-$HOME/.cache/cao-xr/foreign}}"
nibabel=(anatomical.nii reoriented_anat_moved.nii standard.nii.gz example4d.nii.gz example_nifti2.nii.gz)
itk=(KmeansTest_T1UCharRaw.nii.gz BrainProtonDensity3Slices.mha BrainProtonDensity3Slices.raw)
missing=0
for f in "${nibabel[@]}" "${itk[@]}" ch2bet.nii.gz; do [ -f "$dest/$f" ] || missing=1; done
[ $missing = 0 ] && exit 0
mkdir -p "$dest"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cd "$work"
pkgs=(python3-nibabel mricron-data insighttoolkit5-examples)
apt-get download -q "${pkgs[@]}" >/dev/null 2>&1 || {
  # the package lists may be missing or stale on a machine that had everything installed
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  apt-get download -q "${pkgs[@]}" >/dev/null
}
for deb in *.deb; do dpkg-deb -x "$deb" x; done
for f in "${nibabel[@]}"; do cp "x/usr/lib/python3/dist-packages/nibabel/tests/data/$f" "$dest/"; done
for f in "${itk[@]}"; do cp "x/usr/share/doc/insighttoolkit5-examples/examples/Data/$f" "$dest/"; done
cp x/usr/share/mricron/templates/ch2bet.nii.gz "$dest/"
echo "foreign-data: nibabel's, mricron's and ITK's volumes in $dest" >&2
