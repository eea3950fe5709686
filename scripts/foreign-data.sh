#!/usr/bin/env bash
# Fetches volumes that nobody on this project wrote, for tests/foreign.rs, into DIR (default
# $CAO_XR_FOREIGN_DATA, else ~/.cache/cao-xr/foreign): nibabel's NIfTI test files (Debian's
# python3-nibabel, unpacked only: it is not installed) and the Colin27 MRI template that mricron
# ships (mricron-data). Downloaded from Debian's archive with `apt-get download`, never committed.
# Cached: a second run does nothing.
set -euo pipefail
dest="${1:-${CAO_XR_FOREIGN_DATA:-$HOME/.cache/cao-xr/foreign}}"
[ -f "$dest/.complete" ] && exit 0
mkdir -p "$dest"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cd "$work"
apt-get download -q python3-nibabel mricron-data >/dev/null 2>&1 || {
  # the package lists may be missing or stale on a machine that had everything installed
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  apt-get download -q python3-nibabel mricron-data >/dev/null
}
for deb in *.deb; do dpkg-deb -x "$deb" x; done
nib=x/usr/lib/python3/dist-packages/nibabel/tests/data
for f in anatomical.nii reoriented_anat_moved.nii standard.nii.gz example4d.nii.gz example_nifti2.nii.gz; do
  cp "$nib/$f" "$dest/"
done
cp x/usr/share/mricron/templates/ch2bet.nii.gz "$dest/"
touch "$dest/.complete"
echo "foreign-data: nibabel's and mricron's NIfTI files in $dest" >&2
