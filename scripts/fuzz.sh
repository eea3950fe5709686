#!/usr/bin/env bash
# Runs every fuzz target (fuzz/fuzz_targets: nrrd, nifti, metaimage, transfer_json, dicom, mesh,
# environment_hdr, pose_stream) for a bounded time each: scripts/fuzz.sh [SECONDS_PER_TARGET] (default 60).
# Installs cargo-fuzz if missing. cargo fuzz needs nightly-only rustc flags; on the stable
# toolchain RUSTC_BOOTSTRAP=1 allows them. New inputs go to fuzz/corpus/TARGET (not committed),
# the committed seeds in fuzz/seeds/TARGET are read too, and a crash stops the script with the
# reproducer in fuzz/artifacts/TARGET (re-run: cargo fuzz run TARGET fuzz/artifacts/TARGET/...).
set -euo pipefail
secs="${1:-60}"
cd "$(dirname "$0")/.."
if ! command -v cargo >/dev/null; then
    echo "fuzz.sh: cargo not found (scripts/setup.sh installs Rust)" >&2
    exit 1
fi
if ! cargo fuzz --version >/dev/null 2>&1; then
    echo "fuzz.sh: installing cargo-fuzz" >&2
    cargo install cargo-fuzz --locked
fi
export RUSTC_BOOTSTRAP=1
targets=(nrrd nifti metaimage transfer_json pose_stream dicom mesh environment_hdr)
# One build for all targets (ASan on: out-of-bounds and use-after-free would show too).
cargo fuzz build -O
for t in "${targets[@]}"; do
    mkdir -p "fuzz/corpus/$t"
    echo "fuzz.sh: $t for ${secs} s" >&2
    cargo fuzz run -O "$t" "fuzz/corpus/$t" "fuzz/seeds/$t" -- \
        -max_total_time="$secs" -rss_limit_mb=4096 -max_len=65536 -print_final_stats=1
done
echo "fuzz.sh: ${#targets[@]} targets ran ${secs} s each without a crash"
